"""Outputs are written whole or not at all: a full disk or a file-size limit during a write
leaves the previous file, removes the partial one and ends in one line naming the file, what
it needs and what its disk has free."""

from __future__ import annotations

import errno
import re
import subprocess
import sys
from pathlib import Path

import pytest
import xarray as xr

import cloudct
from cloudct.cli import main
from cloudct.netcdf import save_netcdf
from cloudct.output_files import OutputInUse, WriteError, exclusive

LES = str(Path(cloudct.__file__).parent / "data" / "rico32x37x26.txt")  # the single cloud


def _les2nc(out, *extra) -> list[str]:
    return ["les2nc", LES, "-o", str(out), "--overwrite", *extra]


def test_a_full_disk_keeps_the_previous_file_and_says_so_in_one_line(tmp_path, capsys,
                                                                     monkeypatch):
    out = tmp_path / "medium.nc"
    assert main(_les2nc(out)) == 0
    before = out.read_bytes()
    capsys.readouterr()
    write = xr.Dataset.to_netcdf

    def fill_the_disk(self, path, *args, **kwargs):  # half a file, then ENOSPC
        write(self, path, *args, **kwargs)
        with open(path, "r+b") as f:
            f.truncate(len(before) // 2)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", fill_the_disk)
    assert main(_les2nc(out, "--source", "another")) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"cloudct les2nc: error: could not write {out} (")
    assert "No space left on device" in err and "MiB free there; the previous file is kept" in err
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["medium.nc"]  # no partial file
    with pytest.raises(WriteError, match="nothing was written"):
        save_netcdf(xr.Dataset({"a": ("t", [1.0])}), tmp_path / "new.nc")
    assert not (tmp_path / "new.nc").exists()


def test_a_file_size_limit_keeps_the_previous_file(tmp_path):
    out = tmp_path / "medium.nc"
    assert main(_les2nc(out)) == 0
    before = out.read_bytes()
    limited = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000)); "
               "from cloudct.cli import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.run([sys.executable, "-c", limited, *_les2nc(out, "--source", "x")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"cloudct les2nc: error: could not write {out}")
    assert "files of at most 0.02 MiB (ulimit -f); the previous file is kept" in err[0]
    assert out.read_bytes() == before and len(before) > 20000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["medium.nc"]


def test_a_second_run_on_the_same_output_is_refused_naming_the_first(tmp_path, capsys):
    out = tmp_path / "result.nc"
    hold = ("import sys, time; from cloudct.output_files import exclusive\n"
            "with exclusive(sys.argv[1]):\n    print('held', flush=True); time.sleep(120)")
    first = subprocess.Popen([sys.executable, "-c", hold, str(out)], stdout=subprocess.PIPE,
                             text=True)
    try:
        assert first.stdout.readline().strip() == "held"
        assert main(["retrieve", str(tmp_path / "measurements.nc"), "-o", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert re.fullmatch(f"cloudct retrieve: error: {re.escape(str(out))} is being written "
                            rf"by process {first.pid} \(cloudct, started [-0-9: ]+\): wait for "
                            r"it to end, or write elsewhere \(-o\)", err), err
    finally:
        first.kill()
        first.wait()
    # the first process gone, its lock went with it: the run goes on to its own errors
    assert main(["retrieve", str(tmp_path / "measurements.nc"), "-o", str(out)]) == 2
    assert "measurement file" in capsys.readouterr().err and not out.exists()


def test_an_output_in_a_missing_folder_is_refused_before_any_work(tmp_path, capsys):
    out = tmp_path / "no" / "such" / "r.nc"
    assert main(["retrieve", str(tmp_path / "measurements.nc"), "-o", str(out)]) == 2
    assert capsys.readouterr().err.strip() == (
        f"cloudct retrieve: error: the folder of {out} does not exist (create it first)")


def test_the_lock_file_goes_with_its_block_and_a_stale_one_holds_no_one_back(tmp_path):
    import fcntl

    out, lock = tmp_path / "r.nc", tmp_path / ".r.nc.lock"
    with exclusive(out):
        assert lock.exists()
        with pytest.raises(OutputInUse), exclusive(out):
            pass
        stale = open(lock)  # opened before the holder's end, as a racing process might
    assert not lock.exists()
    fcntl.flock(stale, fcntl.LOCK_EX | fcntl.LOCK_NB)  # the racer locks the removed file
    with exclusive(out):  # which holds back no one: the path's lock is a new file
        assert lock.exists()
    stale.close()
    assert not lock.exists()
