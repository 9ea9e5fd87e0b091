"""Faults: killed precomputes, damaged checkpoints and .hfr files (issue 26, items 5 and 6).

Process tests start a real ``hfrad precompute`` in a subprocess (its own
session, so a test can signal its whole process group as a terminal's Ctrl-C
does), wait until both form-factor workers run (Embree mapped), then kill or
signal it and check what is left: processes, shared memory, the checkpoint.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from conftest import Interrupt, default_sigint, interrupt_at, run_cli

from hfrad import Checkpoint, PrecomputeOptions
from hfrad import factorize, load_scene
from hfrad.errors import FileFormatError, InputError
from hfrad.lowrank.streaming import load_checkpoint
from hfrad.integrity import DIGEST, integrity_problem
from hfrad.formfactors.parallel import SEGMENT_PREFIX, remove_stale_segments
from hfrad.solve.hfr import load_hfr, read_hfr_metadata, save_hfr

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux") or not os.path.isdir("/dev/shm"),
                                reason="reads /proc and /dev/shm (Linux)")

# hfrad's command line with a checkpoint after the first block, and no more: the default waits 30 s;
# and a Ctrl-C that lands in a garbage-collection callback (frequent while h5py writes a file per
# block) is swallowed by Python ("Exception ignored in ..."), so the run would go on
_CLI = ("import sys\n"
        "if __name__ == '__main__':\n"
        "    import hfrad.precompute.backends, hfrad.precompute.local\n"
        "    hfrad.precompute.backends.Checkpoint.__init__.__defaults__ = (1e-6, False)\n"
        "    hfrad.precompute.local.CHECKPOINT_COST_RATIO = 1e9\n"
        "    from hfrad.cli import main\n"
        "    sys.argv = ['hfrad', *sys.argv[1:]]\n"
        "    sys.exit(main())\n")


# -- processes ---------------------------------------------------------------------------

def _stat(pid: int) -> tuple[str, int] | None:
    """(state, parent pid) of a process, None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text.rsplit(")", 1)[1].split()
    return fields[0], int(fields[1])


def _running(pid: int) -> bool:
    st = _stat(pid)
    return st is not None and st[0] != "Z"   # a zombie has exited (nobody reaped it yet)


def _children(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            st = _stat(int(d))
            if st is not None and st[1] == pid:
                out.append(int(d))
    return out


def _workers_busy(pid: int) -> list[int]:
    """The parent's spawned workers that have built their Embree scene (initialised, computing)."""
    busy = []
    for c in _children(pid):
        try:
            if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes() and \
                    "embree" in Path(f"/proc/{c}/maps").read_text():
                busy.append(c)
        except OSError:
            continue
    return busy


def _segments(pid: int) -> list[str]:
    return sorted(n for n in os.listdir("/dev/shm") if n.startswith(f"{SEGMENT_PREFIX}{pid}_"))


class _Precompute:
    """``hfrad precompute cornell`` with two form-factor workers in a subprocess of its own session."""

    def __init__(self, tmp_path: Path, patches: int = 2400):
        self.output = tmp_path / "x.hfr"
        self.checkpoint = tmp_path / "x.hfr.partial"
        self.stderr = tmp_path / "stderr.txt"
        args = ["precompute", "cornell", "--patches", str(patches), "--processes", "2", "--block", "16",
                "--near-field", "off", "-o", str(self.output), "--quiet"]
        with open(self.stderr, "wb") as err:
            self.proc = subprocess.Popen([sys.executable, "-c", _CLI, *args], cwd=tmp_path, stdout=subprocess.DEVNULL,
                                         stderr=err, start_new_session=True,
                                         preexec_fn=default_sigint)
        self.children: list[int] = []

    def wait_busy(self, timeout: float = 180.0, checkpoint: bool = False) -> list[int]:
        """Wait until both workers compute (and a checkpoint exists, if asked); returns the workers."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            assert self.proc.poll() is None, f"precompute ended early: {self.stderr.read_text()[-2000:]}"
            busy = _workers_busy(self.proc.pid)
            if len(busy) == 2 and (not checkpoint or self.checkpoint.exists()):
                self.children = _children(self.proc.pid)   # the workers and the resource tracker
                return busy
            time.sleep(0.1)
        pytest.fail(f"the workers did not start within {timeout} s")

    def survivors(self, timeout: float) -> list[int]:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            left = [c for c in self.children if _running(c)]
            if not left:
                return []
            time.sleep(0.1)
        return left

    def cleanup(self) -> None:
        for pid in [self.proc.pid, *self.children]:
            if _running(pid):
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        self.proc.wait(timeout=30)


@pytest.fixture
def precompute(tmp_path):
    runs = []

    def start(**kwargs):
        runs.append(_Precompute(tmp_path, **kwargs))
        return runs[-1]

    yield start
    for run in runs:
        run.cleanup()


@linux_only
def test_kill_9_leaves_no_worker_and_no_shared_memory(precompute):
    """kill -9 of the parent: its workers exit at once and its shared memory is unlinked."""
    run = precompute()
    run.wait_busy()
    assert len(_segments(run.proc.pid)) == 2
    t0 = time.monotonic()
    os.kill(run.proc.pid, signal.SIGKILL)
    run.proc.wait(timeout=30)
    assert run.survivors(timeout=10.0) == [], "orphaned workers"
    print(f"children gone {time.monotonic() - t0:.2f} s after kill -9")
    t_shm = time.monotonic()
    while _segments(run.proc.pid) and time.monotonic() - t_shm < 5.0:
        time.sleep(0.1)
    assert _segments(run.proc.pid) == []


@linux_only
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_and_sigterm_stop_cleanly_and_keep_the_checkpoint(precompute, signum):
    """Ctrl-C (SIGINT to the process group) or SIGTERM: a quick exit without tracebacks, no
    process left, and an intact checkpoint that a rerun resumes from.

    SIGTERM ends the parent at once (its default action; the workers follow it): a checkpoint
    being written then leaves its temporary file, which the next write of it removes
    (hfrad.atomic). Ctrl-C unwinds, and the atomic writer removes its temporary file itself.
    """
    run = precompute()
    run.wait_busy(checkpoint=True)
    if signum == signal.SIGINT:
        os.killpg(run.proc.pid, signum)   # what a terminal sends on Ctrl-C
    else:
        os.kill(run.proc.pid, signum)
    t0 = time.monotonic()
    code = run.proc.wait(timeout=60)
    seconds = time.monotonic() - t0
    err = run.stderr.read_text()
    assert code != 0 and "Traceback" not in err and "Error" not in err, err[-3000:]
    assert run.survivors(timeout=10.0) == []
    assert seconds < 20, f"took {seconds:.1f} s to stop"
    with h5py.File(run.checkpoint, "r") as f:
        assert integrity_problem(f) is None and int(f.attrs["blocks_done"]) > 0
    if signum == signal.SIGINT:
        assert not list(run.checkpoint.parent.glob(".*.tmp*")), "a temporary file was left behind"


@linux_only
def test_a_killed_worker_is_one_clear_error(precompute):
    """A worker killed -9 mid-run (the OOM killer): exit 2 with one line, not a hang, no process left."""
    run = precompute()
    workers = run.wait_busy()
    os.kill(workers[0], signal.SIGKILL)
    code = run.proc.wait(timeout=60)
    err = run.stderr.read_text()
    assert code == 2, err[-3000:]
    assert "worker process exited" in err and "Traceback" not in err, err[-3000:]
    assert run.survivors(timeout=10.0) == []
    assert _segments(run.proc.pid) == []


def test_a_worker_dead_before_the_next_submit_is_the_same_clear_error():
    """A worker killed between two blocks breaks the pool before the next submit (seen on a
    fast CI machine): that is the dead-worker message too, not an internal error."""
    from concurrent.futures.process import BrokenProcessPool

    from hfrad.errors import WorkerError
    from hfrad.formfactors.parallel import _submit

    class Broken:
        def submit(self, *args, **kwargs):
            raise BrokenProcessPool("A child process terminated abruptly")

    with pytest.raises(WorkerError, match="worker process exited"):
        _submit(Broken(), 0, np.arange(3), slice(0, 0))


@linux_only
def test_stale_segments_of_dead_creators_are_removed(tmp_path):
    """Segments named after a process that no longer runs are unlinked once old enough; others stay."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    names = {"dead_old": f"{SEGMENT_PREFIX}{dead.pid}_0a1b", "dead_new": f"{SEGMENT_PREFIX}{dead.pid}_2c3d",
             "alive_old": f"{SEGMENT_PREFIX}{os.getpid()}_4e5f"}
    try:
        for key, name in names.items():   # what SharedMemory(name, create=True) makes on Linux
            Path(f"/dev/shm/{name}").write_bytes(bytes(16))
            if key.endswith("_old"):
                os.utime(f"/dev/shm/{name}", (time.time() - 3600, time.time() - 3600))
        removed = remove_stale_segments(min_age=60.0)
        assert names["dead_old"] in removed
        present = set(os.listdir("/dev/shm"))
        assert names["dead_old"] not in present
        assert names["dead_new"] in present and names["alive_old"] in present
    finally:
        for name in names.values():
            Path(f"/dev/shm/{name}").unlink(missing_ok=True)


# -- checkpoints ---------------------------------------------------------------------------

_OPTS = dict(eps=0.02, dtype="float64", options=PrecomputeOptions(block_size=32))


@pytest.fixture(scope="module")
def cornell():
    return load_scene("cornell", patches=300)


@pytest.fixture(scope="module")
def checkpoint_file(cornell, tmp_path_factory):
    """A checkpoint after three blocks of a 300-patch Cornell box."""
    path = tmp_path_factory.mktemp("ckpt") / "run.partial"
    with pytest.raises(Interrupt):
        factorize(cornell, status=interrupt_at(4), checkpoint=Checkpoint(path, interval=0.0), **_OPTS)
    return path


def _data_offset(ds) -> tuple[int, int]:
    """File offset and size of a dataset's first chunk (or its contiguous data)."""
    if ds.chunks:
        info = ds.id.get_chunk_info(0)
        return info.byte_offset, info.size
    return ds.id.get_offset(), ds.id.get_storage_size()


def _flip_bit(path: Path, dataset: str) -> None:
    with h5py.File(path, "r") as f:
        offset, size = _data_offset(f[dataset])
    with open(path, "r+b") as fh:
        fh.seek(offset + size // 2)
        b = fh.read(1)
        fh.seek(offset + size // 2)
        fh.write(bytes([b[0] ^ 0x10]))


def _damage(path: Path, how: str) -> None:
    if how == "bit flip in a factor":
        _flip_bit(path, "node0/U")
    elif how == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "a PNG":
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    elif how == "counter edited":
        with h5py.File(path, "a") as f:
            f.attrs["blocks_done"] = int(f.attrs["blocks_done"]) - 1
    elif how == "digest deleted, counter edited":
        with h5py.File(path, "a") as f:
            f.attrs.pop(DIGEST, None)
            f.attrs["blocks_done"] = int(f.attrs["blocks_done"]) - 1
    elif how == "array rewritten without checksum":
        with h5py.File(path, "a") as f:
            U = f["node0/U"][()]
            del f["node0/U"]
            f.create_dataset("node0/U", data=1.5 * U)
    elif how == "array deleted":
        with h5py.File(path, "a") as f:
            del f["extra/" + sorted(f["extra"])[0]]
    else:  # pragma: no cover
        raise AssertionError(how)


@pytest.mark.parametrize("how", ["bit flip in a factor", "truncated", "empty", "a PNG", "counter edited",
                                 "digest deleted, counter edited", "array rewritten without checksum",
                                 "array deleted"])
def test_damaged_checkpoint_is_refused(cornell, checkpoint_file, tmp_path, how):
    """A damaged checkpoint is refused naming the file, before any work, and is not deleted."""
    bad = tmp_path / "run.partial"
    bad.write_bytes(checkpoint_file.read_bytes())
    _damage(bad, how)
    with pytest.raises(FileFormatError, match=r"run\.partial: .*(damaged|not a readable).*delete it"):
        factorize(cornell, checkpoint=bad, **_OPTS)
    assert bad.exists()


def test_checkpoint_of_other_options_or_version_is_refused(cornell, checkpoint_file, tmp_path):
    other = tmp_path / "other.partial"
    other.write_bytes(checkpoint_file.read_bytes())
    with pytest.raises(InputError, match="another scene or other parameters"):
        factorize(cornell, checkpoint=other, **{**_OPTS, "eps": 0.05})
    with pytest.raises(InputError, match="another scene or other parameters"):
        factorize(load_scene("cornell", patches=250), checkpoint=other, **_OPTS)
    # a version-1 checkpoint (no checksums: it cannot be verified)
    with h5py.File(other, "a") as f:
        for name in ("format", "datasets", DIGEST):
            del f.attrs[name]
        f.attrs["version"] = 1
    with pytest.raises(FileFormatError, match="checkpoint version 1"):
        load_checkpoint(other, "")


def test_checkpoint_round_trip_is_verified(checkpoint_file):
    """The intact checkpoint passes its checks and every array carries a checksum."""
    with h5py.File(checkpoint_file, "r") as f:
        assert integrity_problem(f) is None
        arrays = []
        f.visititems(lambda n, o: arrays.append(o) if isinstance(o, h5py.Dataset) and o.size > 1 else None)
        assert arrays and all(ds.fletcher32 for ds in arrays)


def test_cli_refuses_a_truncated_checkpoint_in_one_line(tmp_path):
    out = tmp_path / "box.hfr"
    ckpt = tmp_path / "box.hfr.partial"
    ckpt.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(100))
    result = run_cli("precompute", "cornell", "--patches", "300", "-o", out, "--quiet")
    assert result.exit_code == 2, result.output
    assert "box.hfr.partial" in result.output and "delete it" in result.output
    assert "Traceback" not in result.output and ckpt.exists() and not out.exists()


def test_checkpoint_survives_until_the_hfr_is_saved(tmp_path, monkeypatch):
    """A crash while writing the .hfr (disk full, kill) keeps the checkpoint; the rerun resumes."""
    import hfrad.precompute.backends
    import hfrad.solve.hfr

    out, ckpt = tmp_path / "box.hfr", tmp_path / "box.hfr.partial"
    monkeypatch.setattr(hfrad.precompute.backends.Checkpoint.__init__, "__defaults__", (0.0, False))

    def crash(*args, **kwargs):
        raise OSError(28, "No space left on device")

    args = ("precompute", "cornell", "--patches", "300", "--block", "32", "-o", out, "--quiet")
    with monkeypatch.context() as m:
        m.setattr(hfrad.solve.hfr, "save_hfr", crash)
        result = run_cli(*args)
    assert result.exit_code != 0 and not out.exists()
    assert ckpt.exists(), "the checkpoint was deleted before the result was saved"
    result = run_cli(*args)
    assert result.exit_code == 0, result.output
    assert out.exists() and not ckpt.exists()


# -- .hfr files ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def hfr_file(cornell, tmp_path_factory):
    """A near-field factorization (so that it has N) of the 300-patch box, saved."""
    fac = factorize(cornell, eps=0.05, near_field=16)
    assert fac.N is not None and fac.N.nnz > 0
    return save_hfr(fac, tmp_path_factory.mktemp("hfr") / "box.hfr"), fac


def _tamper(path: Path, how: str) -> None:
    with h5py.File(path, "a") as f:
        if how == "digest deleted":
            del f.attrs[DIGEST]
        elif how == "digest deleted, error edited":
            del f.attrs[DIGEST]
            f.attrs["achieved_error"] = 1e-9
        elif how == "checksum removed, factor edited":
            Q = f["factors/Q"][()]
            del f["factors/Q"]
            f.create_dataset("factors/Q", data=1.01 * Q)
        elif how == "near field deleted":
            for k in ("near_data", "near_indices", "near_indptr"):
                del f[f"factors/{k}"]
        elif how == "statistics deleted":
            del f["stats"]
        else:  # pragma: no cover
            raise AssertionError(how)


@pytest.mark.parametrize("how", ["digest deleted", "digest deleted, error edited",
                                 "checksum removed, factor edited", "near field deleted", "statistics deleted"])
def test_hfr_without_its_checks_is_refused(hfr_file, tmp_path, how):
    path, _ = hfr_file
    bad = tmp_path / "bad.hfr"
    bad.write_bytes(path.read_bytes())
    _tamper(bad, how)
    with pytest.raises(FileFormatError, match=r"bad\.hfr: damaged \.hfr file"):
        load_hfr(bad)
    with pytest.raises(FileFormatError, match="damaged"):
        read_hfr_metadata(bad)


@pytest.mark.parametrize("fraction", [0.0, 0.001, 0.1, 0.5, 0.9, 0.999])
def test_truncated_hfr_is_refused(hfr_file, tmp_path, fraction):
    path, _ = hfr_file
    data = path.read_bytes()
    bad = tmp_path / "cut.hfr"
    bad.write_bytes(data[: int(fraction * len(data))])
    with pytest.raises(FileFormatError, match=r"cut\.hfr"):
        load_hfr(bad)


def test_hfr_that_is_not_one_is_refused_by_the_cli(hfr_file, tmp_path):
    png = tmp_path / "picture.hfr"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(500))
    folder = tmp_path / "folder.hfr"
    folder.mkdir()
    bad = tmp_path / "bad.hfr"
    bad.write_bytes(hfr_file[0].read_bytes())
    _tamper(bad, "digest deleted")
    for path in (png, folder, bad):
        result = run_cli("solve", path, "-o", tmp_path / "b.npz")
        assert result.exit_code == 2, result.output
        assert path.name in result.output and "Traceback" not in result.output


def test_intact_hfr_still_loads(hfr_file):
    path, fac = hfr_file
    back = load_hfr(path)
    E = fac.scene.emission
    np.testing.assert_array_equal(back.solve(E), fac.solve(E))


# -- the form-factor block cache ---------------------------------------------------------------

@pytest.mark.parametrize("how", ["bit flip in F", "F rewritten without checksum", "key edited, digest deleted"])
def test_damaged_form_factor_cache_is_refused(cornell, tmp_path, how):
    """A complete cache that was damaged is refused naming the file, never read as form factors."""
    from hfrad.formfactors.blocks import iter_column_blocks

    path = tmp_path / "ff.h5"
    want = np.concatenate([b for _, _, b in iter_column_blocks(cornell, 100, cache=path)], axis=1)
    with h5py.File(path, "a") as f:
        if how == "F rewritten without checksum":
            F = f["F"][()]
            del f["F"]
            f.create_dataset("F", data=F * 1.01)
        elif how == "key edited, digest deleted":
            del f.attrs[DIGEST]
            f.attrs["key"] = f.attrs["key"].replace('"samples": 16', '"samples": 17')
    if how == "bit flip in F":
        with h5py.File(path, "r") as f:
            offset, size = _data_offset(f["F"])
        with open(path, "r+b") as fh:   # an exponent bit of a float32 in the first chunk
            fh.seek(offset + size // 2 // 4 * 4 + 3)
            b = fh.read(1)
            fh.seek(offset + size // 2 // 4 * 4 + 3)
            fh.write(bytes([b[0] ^ 0x01]))
    with pytest.raises(FileFormatError, match=r"ff\.h5: .*damaged.*delete"):
        got = np.concatenate([b for _, _, b in iter_column_blocks(cornell, 100, cache=path)], axis=1)
        assert np.array_equal(got, want)   # (reached only on the old code: the damage was read)
