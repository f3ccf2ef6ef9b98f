"""OpenEXR's thread pool (kpcn.io.exr_threads): on for kpcn's reads and writes, the same pixels, and safe across fork.

Each case runs in a fresh interpreter: the pool is process-global state."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from kpcn.io import write_exr

#: reads the file in $EXR, prints the pool's thread count and a digest of the pixels; with FORK=1 a forked child
#: (multiprocessing's fork context, as a DataLoader's workers) reads it too and prints its digest
SCRIPT = textwrap.dedent("""
    import hashlib, os, multiprocessing as mp
    import OpenEXR
    from kpcn.io import read_exr, write_exr

    def digest(path):
        f = read_exr(path)
        return hashlib.sha1(b"".join(f.layers[k].tobytes() for k in sorted(f.layers))).hexdigest()

    def child(q, path):
        q.put(digest(path))

    path = os.environ["EXR"]
    print("count", OpenEXR.global_thread_count())
    print("digest", digest(path))
    print("count", OpenEXR.global_thread_count())
    if os.environ.get("FORK"):
        ctx = mp.get_context("fork")
        for _ in range(2):
            q = ctx.Queue()
            p = ctx.Process(target=child, args=(q, path))
            p.start()
            p.join(60)
            if p.is_alive():
                p.kill()
                print("child hung")
            else:
                print("child", q.get(timeout=5))
        print("count", OpenEXR.global_thread_count())
        print("again", digest(path))
        write_exr(path + ".out.exr", read_exr(path).layers)
        print("wrote", digest(path + ".out.exr") == digest(path))
""")


def _run(path, **env):
    full = {**os.environ, "EXR": str(path), **env}
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=full, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return [line.split(" ", 1) for line in done.stdout.splitlines()]


@pytest.fixture(scope="module")
def exr(render, tmp_path_factory):
    path = tmp_path_factory.mktemp("exr") / "frame.exr"
    frame = render("test:textured", spp=4, resolution=(160, 120))
    write_exr(path, frame.layers, frame.meta)
    return path


def test_reads_use_the_pool_and_give_the_same_pixels(exr):
    threaded = dict(_run(exr, KPCN_EXR_THREADS="2"))
    single = _run(exr, KPCN_EXR_THREADS="0")
    assert single[0] == ["count", "0"] and single[2] == ["count", "0"]  # 0: OpenEXR's own single thread
    assert threaded["count"] == "2"
    assert threaded["digest"] == dict(single)["digest"]


def test_a_process_forked_after_a_read_reads_too(exr):
    """Without the fork guard the child's read waits forever for pool threads that were not forked with it."""
    out = _run(exr, KPCN_EXR_THREADS="2", FORK="1")
    digest = dict(out)["digest"]
    children = [v for k, v in out if k in ("child", "child hung")]
    assert children == [digest, digest], out
    assert dict(out)["again"] == digest and dict(out)["wrote"] == "True"
    assert [v for k, v in out if k == "count"][-1] == "2"  # the parent's pool restored after the forks


def test_a_bad_thread_count_is_named(exr):
    env = {**os.environ, "EXR": str(exr), "KPCN_EXR_THREADS": "many"}
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0 and "KPCN_EXR_THREADS" in done.stderr and "'many'" in done.stderr


def test_bench_exr_times_the_pool_against_one_thread(mi, capsys):
    from kpcn.bench import SUBCOMMANDS
    from kpcn.io.exr_threads import MAX_DEFAULT

    rc = SUBCOMMANDS["exr"](["--size", "64", "48", "--repeats", "1", "--threads", "0", "1"])
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.startswith(("default", "KPCN_"))}
    assert rc == 0 and set(rows) == {"default", "KPCN_EXR_THREADS=0", "KPCN_EXR_THREADS=1"}, out
    assert rows["KPCN_EXR_THREADS=0"][1] == "0" and rows["KPCN_EXR_THREADS=1"][1] == "1"
    assert rows["default"][1] == str(min(len(os.sched_getaffinity(0)), MAX_DEFAULT))
    assert rows["KPCN_EXR_THREADS=0"][4:6] == ["1.00", "1.00"]  # the baseline against itself
