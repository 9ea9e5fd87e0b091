"""A Ctrl-C that lands while a finalizer runs stops the command (hfrad.cli.redeliver_interrupts)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

from conftest import default_sigint

SCRIPT = textwrap.dedent("""
    import sys, time
    from hfrad.cli import redeliver_interrupts
    if sys.argv[1] == "hook":
        redeliver_interrupts()

    class Slow:
        def __del__(self):                # a finalizer the garbage collector runs between two lines
            print("in finalizer", flush=True)
            time.sleep(3)                 # the Ctrl-C lands here

    try:
        Slow()
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 5:
            pass
        print("ran on", flush=True)
    except KeyboardInterrupt:
        print("stopped", flush=True)
""")


def interrupt_in_finalizer(mode: str) -> str:
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, mode], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=default_sigint)
    try:
        assert proc.stdout.readline() == "in finalizer\n"
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    return out


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_ctrl_c_in_a_finalizer_stops_the_command():
    assert interrupt_in_finalizer("plain") == "ran on\n"      # Python swallows it ("Exception ignored")
    assert interrupt_in_finalizer("hook") == "stopped\n"
