"""Shared helpers of the benchmarks: peak-RSS measurement and table formatting."""





def _proc_status_kb(field: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def _reset_peak_rss() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_rss_kb(reset_ok: bool) -> tuple[int, str]:
    """Peak RSS (kB) since the last reset, and how it was measured."""
    if reset_ok and _proc_status_kb("VmHWM") is not None:
        return _proc_status_kb("VmHWM"), "VmHWM (reset via /proc/self/clear_refs) - VmRSS before"
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "ru_maxrss - VmRSS before (may over-report)"


def _mem_available_bytes() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None



def _fmt_s(r: dict) -> str:
    if r.get("status") != "ok":
        return r.get("status", "?")
    return f"{r['median_s']:.3f} (min {r['min_s']:.3f})"


def _fmt_mb(r: dict) -> str:
    if r.get("status") != "ok":
        return "-"
    return f"{r['mem_mb']:.0f}"


def _ratio(a: dict, b: dict, key: str) -> str:
    if a.get("status") != "ok" or b.get("status") != "ok":
        return "n/a"
    den = max(b[key], 1.0 if key == "mem_mb" else 1e-9)  # memory: at least 1 MB to avoid dividing by noise
    return f"{a[key] / den:.1f}x"




def _isolated_worker(conn, fn, *args) -> None:
    try:
        result = fn(*args)
    except BaseException as exc:  # report, do not hang the parent
        result = {"status": f"failed: {type(exc).__name__}: {exc}"}
    conn.send(result)
    conn.close()


def run_isolated(fn, args: tuple, timeout: float) -> dict:
    """``fn(*args)`` (a module-level function returning a dict) in a fresh spawned process, so its memory
    is its own; stopped after ``timeout`` s. A timeout or a dead worker gives ``{"status": ...}``."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_isolated_worker, args=(send, fn, *args))
    proc.start()
    send.close()
    result = None
    try:
        if recv.poll(timeout):
            result = recv.recv()
    except EOFError:  # the worker died without answering
        result = None
    if result is None:
        alive = proc.is_alive()
        if alive:
            proc.terminate()  # the worker this call started
        proc.join(10)
        return {"status": f"timeout (> {timeout:.0f} s)" if alive
                else f"failed (worker died, exit code {proc.exitcode}: out of memory?)"}
    proc.join(10)
    return result
