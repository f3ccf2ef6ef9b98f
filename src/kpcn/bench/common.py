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


