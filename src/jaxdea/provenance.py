"""Which files jaxdea wrote: the mark every output file carries, read back before a file
of that name is replaced.

Why: a command run twice should replace its own output, but never a file it did not write
(measured data, a hand-written config, a figure made elsewhere): a typo in ``--out`` must not
cost a researcher their data. So every file jaxdea writes says so, in the way its format
allows, and a writer refuses, before any compute, to replace a file without that mark:

- NetCDF and Zarr datasets: the attribute ``jaxdea_version``;
- PNG figures: the text chunk ``Software = "jaxdea <version>"``;
- TOML configs: a first comment line ``# written by jaxdea <version>``.
"""

from __future__ import annotations

import struct
from importlib import metadata
from pathlib import Path

from ._checks import JaxdeaError

#: The comment that marks a TOML config jaxdea wrote.
MARK = "written by jaxdea"
_PNG = b"\x89PNG\r\n\x1a\n"


def jaxdea_version() -> str:
    """The installed jaxdea version (``"unknown"`` in a source tree without install)."""
    try:
        return metadata.version("jaxdea")
    except metadata.PackageNotFoundError:  # pragma: no cover - source tree without install
        return "unknown"


def toml_mark() -> str:
    """The first line of a TOML config jaxdea writes."""
    return f"# {MARK} {jaxdea_version()}\n"


def figure_metadata(path) -> dict[str, str] | None:
    """``savefig(path, metadata=...)`` of a figure jaxdea writes: the mark for a PNG, None
    (matplotlib's default) for other formats, which have no such text chunk."""
    return {"Software": f"jaxdea {jaxdea_version()}"} if str(path).endswith(".png") else None


def _png_software(path: Path) -> str:
    """The ``Software`` text chunk of a PNG ("" if none), read up to the image data."""
    with path.open("rb") as fh:
        if fh.read(8) != _PNG:
            return ""
        while True:
            head = fh.read(8)
            if len(head) < 8:
                return ""
            size, kind = struct.unpack(">I4s", head)
            if kind in (b"IDAT", b"IEND"):
                return ""
            data = fh.read(size)
            fh.read(4)  # CRC
            if kind == b"tEXt" and data.startswith(b"Software\x00"):
                return data[len(b"Software\x00"):].decode("latin-1")
            if kind == b"iTXt" and data.startswith(b"Software\x00"):
                return data.rsplit(b"\x00", 1)[-1].decode("utf-8", "replace")


def written_by_jaxdea(path: str | Path) -> bool:
    """Whether ``path`` (a file, or a Zarr folder) carries jaxdea's mark (module docstring);
    anything unreadable is not jaxdea's."""
    path = Path(path)
    try:
        if path.suffix in (".nc", ".zarr"):
            import xarray as xr

            if path.suffix == ".nc":
                if not path.is_file():
                    return False
                with xr.open_dataset(path, engine="h5netcdf") as ds:
                    return "jaxdea_version" in ds.attrs
            if not path.is_dir():
                return False
            with xr.open_zarr(path, consolidated=False) as ds:
                return "jaxdea_version" in ds.attrs
        if not path.is_file():
            return False
        if path.suffix == ".png":
            return _png_software(path).startswith("jaxdea")
        if path.suffix == ".toml":
            with path.open(encoding="utf-8", errors="replace") as fh:
                return fh.readline().startswith(f"# {MARK}")
    except Exception:  # noqa: BLE001 - anything unreadable is not ours
        return False
    return False


def check_replaceable_file(path: str | Path, name: str,
                           error: type[JaxdeaError] = JaxdeaError) -> None:
    """Refuse (raise ``error``, one line naming ``name``) to write ``path`` over an existing
    file that jaxdea did not write; a missing path or a jaxdea output passes."""
    path = Path(path)
    if path.is_file() and not written_by_jaxdea(path):
        raise error(f"{name} {path} exists and jaxdea did not write it: refusing to replace "
                    "it; choose another name, or move the file away")
