"""Nothing of the user's is ever deleted by a power map, and two runs never share a store
(issue 13, item 3 and the lock): a store is replaced only when jaxdea wrote it, a lock file
admits one run at a time and is released on Ctrl-C."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from jaxdea import SweepError
from jaxdea.cli import main
from jaxdea.studies.mapstore import StoreLock, check_replaceable, is_jaxdea_store, write_store

LS = str(Path(__file__).resolve().parents[1] / "configs" / "dcdea_ls.toml")


def _user_folder(tmp_path: Path, name: str) -> Path:
    folder = tmp_path / name
    (folder / "sub").mkdir(parents=True)
    (folder / "sub" / "notes.txt").write_text("data")
    return folder


def test_a_users_folder_or_file_is_never_replaced(tmp_path):
    folder = _user_folder(tmp_path, "important.zarr")
    with pytest.raises(SweepError, match="is not a jaxdea power map"):
        check_replaceable(folder)
    user_nc = tmp_path / "mine.nc"
    user_nc.write_text("not netcdf")
    with pytest.raises(SweepError, match="a file of that name exists"):
        check_replaceable(user_nc)
    check_replaceable(tmp_path / "new.zarr")  # nothing there: fine
    assert (folder / "sub" / "notes.txt").read_text() == "data"


@pytest.mark.parametrize("suffix", [".zarr", ".nc"])
def test_a_jaxdea_store_may_be_replaced(tmp_path, suffix):
    ds = xr.Dataset({"P_out": ("f", np.arange(3.0))}, attrs={"jaxdea_version": "0.1.0"})
    store = tmp_path / f"map{suffix}"
    write_store(ds, store)
    assert is_jaxdea_store(store)
    check_replaceable(store)
    write_store(ds, store)  # replaced in place
    assert is_jaxdea_store(store)


def test_powermap_refuses_a_users_folder_before_any_compute(tmp_path, capsys):
    folder = _user_folder(tmp_path, "important.zarr")
    code = main(["powermap", LS, "--mass", "1e-3:2e-3:2", "--damping", "0.1:1:2",
                 "--freq", "40:60:10", "--cycles", "4", "--average", "2",
                 "--out", str(folder), "--no-progress"])
    assert code == 2
    assert "is not a jaxdea power map" in capsys.readouterr().err
    assert (folder / "sub" / "notes.txt").read_text() == "data"
    assert not (tmp_path / "important.zarr.parts").exists()


def test_a_parts_folder_with_foreign_files_is_not_deleted(tmp_path):
    from jaxdea.studies.mapstore import Parts

    parts = tmp_path / "map.zarr.parts"
    parts.mkdir()
    (parts / "mine.txt").write_text("keep")
    with pytest.raises(SweepError, match="different run"):
        Parts(tmp_path / "map.zarr", {"a": 1}, 2).open(resume=False)
    assert (parts / "mine.txt").read_text() == "keep"


def test_one_run_per_store(tmp_path):
    store = tmp_path / "map.zarr"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = store.with_name("map.zarr.lock")
        lock.write_text(str(other.pid))
        with pytest.raises(SweepError, match=rf"another jaxdea run \(pid {other.pid}\)"):
            with StoreLock(store):
                pass
        assert lock.exists()  # the other run's lock is left alone
    finally:
        other.kill()
        other.wait()
    with StoreLock(store):  # its run is gone: the stale lock is taken over
        assert lock.read_text().strip().isdigit()
    assert not lock.exists()  # released


def test_the_lock_is_released_on_interrupt(tmp_path):
    store = tmp_path / "map.zarr"
    with pytest.raises(KeyboardInterrupt):
        with StoreLock(store):
            raise KeyboardInterrupt
    assert not store.with_name("map.zarr.lock").exists()
