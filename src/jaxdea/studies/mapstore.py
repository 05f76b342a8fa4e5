"""On-disk side of :func:`jaxdea.powermap`: chunk parts, the run manifest, the final store.

Why: a full power map is hours of compute, so a killed run must lose at most the chunk in
flight. Each finished chunk is written at once to ``<store>.parts/chunk_NNNNNN.npz`` (a temp
name, then ``os.replace``, so a chunk file is either complete or absent). The parts folder also
holds ``manifest.json`` with a hash of every setting that determines the result; a resumed run
only reuses chunks whose manifest hash matches its own, so parts of a different run are never
mixed in. When all chunks are done the Dataset is written to the final store (NetCDF or Zarr,
by suffix), again via a temp name renamed into place, and the parts folder is removed.

The folder is safe to share (cluster workers write their parts into it, :mod:`.distributed`):
every part records its chunk index, its cell range and a SHA-256 of its arrays, and a part that
is unreadable, truncated, empty, of another run or of another chunk is recomputed with a
:class:`PartWarning` naming the file, never mixed in silently.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from .._checks import SweepError
from ..provenance import written_by_jaxdea

SUFFIXES = (".zarr", ".nc")
MANIFEST = "manifest.json"


def parts_dir(store: Path) -> Path:
    """``<store>.parts``: the folder of a run's finished chunks (:class:`Parts`), beside
    ``store`` while the run is unfinished."""
    return store.with_name(store.name + ".parts")


def check_store_path(store: str | os.PathLike) -> Path:
    """The store path, checked: it must end in .zarr or .nc."""
    path = Path(store)
    if path.suffix not in SUFFIXES:
        raise SweepError(f"store must end in .zarr (Zarr) or .nc (NetCDF), got {str(path)!r}")
    return path


def is_jaxdea_store(path: Path) -> bool:
    """Whether ``path`` holds a power map that jaxdea wrote (its attrs name a jaxdea version)."""
    return path.suffix in SUFFIXES and written_by_jaxdea(path)


def check_replaceable(store: Path) -> None:
    """Refuse (before any compute) to write ``store`` over anything jaxdea did not write: only
    a missing path or an existing jaxdea power map may be replaced, never a user's file or
    folder."""
    if (store.exists() or store.is_symlink()) and not is_jaxdea_store(store):
        kind = "folder" if store.is_dir() else "file"
        raise SweepError(f"refusing to write the map to {store}: a {kind} of that name exists "
                         "and is not a jaxdea power map; choose another output path or move it")


class StoreLock:
    """``<store>.lock``: one run at a time per store. Created atomically with the owner's pid;
    a lock whose process is gone is taken over; released on exit (also on Ctrl-C)."""

    def __init__(self, store: Path):
        self.path = store.with_name(store.name + ".lock")

    def __enter__(self) -> StoreLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                pid = self._owner()
                if pid is not None and pid != os.getpid() and _alive(pid):
                    raise SweepError(f"another jaxdea run (pid {pid}) is writing this map "
                                     f"({self.path} exists): wait for it to finish, or remove "
                                     "the lock file if that run is gone") from None
                self.path.unlink(missing_ok=True)  # stale: its run is gone
                continue
            with os.fdopen(fd, "w") as fh:
                fh.write(str(os.getpid()))
            return self
        raise SweepError(f"could not take the lock {self.path}: remove it if no run is going")

    def __exit__(self, *exc) -> None:
        if self._owner() == os.getpid():
            self.path.unlink(missing_ok=True)

    def _owner(self) -> int | None:
        try:
            return int(self.path.read_text().strip())
        except (OSError, ValueError):
            return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def settings_hash(settings: dict[str, Any]) -> str:
    """SHA-256 of the canonical JSON of ``settings`` (floats written exactly by ``repr``)."""
    text = json.dumps(settings, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _atomic_write_bytes(path: Path, write) -> None:
    """Write through ``write(fh)`` to a hidden temp file, fsync, then rename into place."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        write(fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _our_temp(name: str) -> bool:
    """A temp file that :func:`_atomic_write_bytes` leaves when killed mid-write."""
    return name.startswith(".") and name.endswith(".tmp")


def previous_chunk_cells(store: Path) -> int | None:
    """The chunk size recorded in ``<store>.parts/manifest.json`` (None: no readable one), so
    that a resumed run keeps the interrupted run's chunks whatever its device or worker
    count."""
    try:
        old = json.loads((parts_dir(store) / MANIFEST).read_text())
        return int(old["settings"]["chunk_cells"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


class PartWarning(UserWarning):
    """A chunk part of an interrupted power map is damaged or not this chunk's: it is
    recomputed (the message names the file)."""


def arrays_sha256(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over the names, dtypes, shapes and bytes of ``arrays`` (in name order)."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


class Parts:
    """The ``<store>.parts`` folder of one run: manifest plus one ``.npz`` per finished chunk."""

    def __init__(self, store: Path, settings: dict[str, Any], n_chunks: int):
        self.dir = parts_dir(store)
        self.settings = settings
        self.hash = settings_hash(settings)
        self.n_chunks = n_chunks
        self.width = max(6, len(str(max(n_chunks - 1, 0))))

    def path(self, i: int) -> Path:
        return self.dir / f"chunk_{i:0{self.width}d}.npz"

    def _differences(self, old: dict[str, Any]) -> list[str]:
        keys = sorted(set(old) | set(self.settings))
        return [k for k in keys if old.get(k) != self.settings.get(k)]

    def open(self, resume: bool) -> set[int]:
        """Prepare the folder; return the chunk indices already finished (resume only).

        Raises :class:`SweepError` when the folder belongs to a different run, or when it
        holds finished chunks of this run but ``resume`` is off (so finished work is never
        discarded silently; a folder of this run with no finished chunk is simply reused).
        """
        manifest = self.dir / MANIFEST
        if self.dir.exists():
            try:
                old = json.loads(manifest.read_text())
            except (OSError, ValueError):
                old = None
            leftovers = [p for p in self.dir.iterdir() if not _our_temp(p.name)]
            if old is None and not leftovers:
                shutil.rmtree(self.dir)  # killed before its manifest was written: nothing lost
                return self.open(resume)
            if old is None or old.get("hash") != self.hash:
                diff = self._differences(old.get("settings", {})) if old else ["(no manifest)"]
                what = "resume" if resume else "start"
                raise SweepError(
                    f"cannot {what}: {self.dir} holds the parts of a different run (settings "
                    f"that differ: {', '.join(diff)}); rerun with the original settings and "
                    f"--resume (resume=True), or delete {self.dir}"
                )
            done = self._finished()
            if not resume and done:
                raise SweepError(
                    f"{self.dir} holds an interrupted run of these settings ({len(done)} of "
                    f"{self.n_chunks} chunks done): pass --resume (resume=True) to continue it, "
                    f"or delete {self.dir}"
                )
            return done
        self.dir.mkdir(parents=True)
        body = {"hash": self.hash, "n_chunks": self.n_chunks, "settings": self.settings}
        _atomic_write_bytes(manifest, lambda fh: fh.write(json.dumps(body, indent=1).encode()))
        return set()

    def _finished(self) -> set[int]:
        return {i for i in range(self.n_chunks) if self.path(i).exists()}

    def save(self, i: int, arrays: dict[str, np.ndarray],
             cells: tuple[int, int] | None = None) -> str:
        """Write chunk ``i`` (flat cells ``cells = (lo, hi)``) atomically, with the run hash,
        the chunk index, the cell range and the SHA-256 of the arrays (all checked on load);
        return that SHA-256."""
        digest = arrays_sha256(arrays)
        lo_hi = np.array(cells if cells is not None else (-1, -1), dtype=np.int64)
        _atomic_write_bytes(self.path(i), lambda fh: np.savez(
            fh, __hash__=np.array(self.hash), __chunk__=np.array(i, dtype=np.int64),
            __cells__=lo_hi, __sha256__=np.array(digest), **arrays))
        return digest

    def load(self, i: int, n: int, names, cells: tuple[int, int] | None = None,
             sha256: str | None = None) -> dict[str, np.ndarray] | None:
        """Chunk ``i`` (``n`` cells, ``cells = (lo, hi)`` when given), or None, with a
        :class:`PartWarning` naming the file, when the part is unreadable (truncated, empty,
        corrupt), of another run or chunk, or its arrays fail their SHA-256 (or differ from
        ``sha256``, a worker's receipt)."""
        path = self.path(i)
        why = None
        try:
            with np.load(path) as z:
                keys = set(z.files)
                if not {"__hash__", "__chunk__", "__cells__", "__sha256__"} <= keys:
                    why = "has no chunk index or checksum (an older jaxdea's part, or not a part)"
                elif str(z["__hash__"]) != self.hash:
                    why = "belongs to a different run (its settings hash differs)"
                elif int(z["__chunk__"]) != i:
                    why = f"holds chunk {int(z['__chunk__'])}, not chunk {i}"
                elif cells is not None and tuple(int(c) for c in z["__cells__"]) != tuple(cells):
                    lo, hi = (int(c) for c in z["__cells__"])
                    why = f"holds cells {lo}-{hi}, not {cells[0]}-{cells[1]}"
                else:
                    out = {k: z[k] for k in names}
                    digest = str(z["__sha256__"])
                    if arrays_sha256(out) != digest or (sha256 is not None and digest != sha256):
                        why = "fails its SHA-256 checksum (corrupt)"
                    elif not all(v.shape == (n,) for v in out.values()):
                        why = f"does not hold {n} cells"
        except Exception as exc:  # noqa: BLE001 - BadZipFile, EOFError, zlib.error, ...
            why = f"is unreadable ({type(exc).__name__}: {exc})"
        if why is None:
            return out
        warnings.warn(f"chunk part {path} {why}: recomputing chunk {i}", PartWarning,
                      stacklevel=2)
        return None

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def _zarr_encoding(ds: xr.Dataset) -> dict[str, dict]:
    """Chunk the grid variables along M, about 1 Mi values per chunk."""
    enc = {}
    for name, var in ds.data_vars.items():
        rest = int(np.prod(var.shape[1:])) if var.ndim > 1 else 1
        first = max(1, min(var.shape[0], (1 << 20) // max(rest, 1))) if var.ndim else None
        if first is not None:
            enc[name] = {"chunks": (first,) + tuple(var.shape[1:])}
    return enc


def write_store(ds: xr.Dataset, store: Path) -> None:
    """Write ``ds`` to ``store`` (.nc: NetCDF4 via h5netcdf; .zarr: Zarr) atomically: a temp
    name is written and renamed into place, so a killed run never leaves a partial store."""
    store = check_store_path(store)
    store.parent.mkdir(parents=True, exist_ok=True)
    tmp = store.with_name(store.name + ".tmp")
    if store.suffix == ".nc":
        ds.to_netcdf(tmp, engine="h5netcdf")
        os.replace(tmp, store)
        return
    if tmp.exists():
        shutil.rmtree(tmp)
    ds.to_zarr(tmp, mode="w", encoding=_zarr_encoding(ds), consolidated=False)
    if store.exists():  # a directory cannot be os.replace'd over a non-empty one
        old = store.with_name(store.name + ".old")
        if old.exists():
            shutil.rmtree(old)
        os.replace(store, old)
        os.replace(tmp, store)
        shutil.rmtree(old)
    else:
        os.replace(tmp, store)


def open_map(path: str | os.PathLike) -> xr.Dataset:
    """Read a power-map store (.zarr or .nc) fully into memory.

    **Arguments:**

    - `path`: the store that :func:`jaxdea.powermap` (or ``jaxdea powermap --out``) wrote.

    **Returns:**

    The map as an ``xarray.Dataset``; :class:`~jaxdea.SweepError` (one line naming the file)
    when it is missing, unreadable, truncated, or not a map (e.g. a sweep file).
    """
    path = Path(path)
    if path.suffix not in SUFFIXES:
        raise SweepError(f"map must be a .zarr or .nc store, got {str(path)!r}")
    if not path.exists():
        raise SweepError(f"map not found: {path}")
    try:
        if path.suffix == ".nc":
            with xr.open_dataset(path, engine="h5netcdf") as ds:
                ds = ds.load()
        else:
            with xr.open_zarr(path, consolidated=False) as ds:
                ds = ds.load()
    except Exception as exc:  # noqa: BLE001 - truncated, foreign or unreadable: one line
        raise SweepError(f"{path} is not a readable power map ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from None
    missing = [k for k in ("M", "f") if k not in ds.dims]
    if missing or "P_out" not in ds or len(set(ds.dims) - {"M", "f", "phase"}) != 1:
        what = "a frequency sweep (jaxdea sweep --plot draws it)" if set(ds.dims) == {"f"} \
            else f"no power map (dims {sorted(map(str, ds.dims))})"
        raise SweepError(f"{path} is {what}: a map has dims M, c (or a payload parameter), f "
                         "and P_out")
    return ds
