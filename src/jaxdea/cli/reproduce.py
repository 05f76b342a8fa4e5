"""``jaxdea reproduce paper000 --out DIR``: paper 000's study regenerated from the fitted set
(Figs 6, 7, 9, 10, 11, claims.md, claims.csv)."""

from __future__ import annotations

import argparse
from pathlib import Path

PAPERS = ("paper000",)


def _out_dir(path: str) -> Path:
    """The output folder: new, empty, or an earlier reproduction (its claims.md there);
    never a folder of other files, which the outputs would overwrite."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "claims.md").exists():
        raise ValueError(f"--out {out}: a non-empty folder that holds no earlier reproduction "
                         "(no claims.md); give a new or empty folder")
    return out


def _reproduce(args) -> int:
    from jaxdea.reproduce.paper000 import CONFIGS
    from jaxdea.reproduce.study import reproduce_paper000

    out = _out_dir(args.out)
    configs = {k: str(Path(args.configs) / Path(v).name) for k, v in CONFIGS.items()}
    for k, v in configs.items():
        if not Path(v).is_file():
            raise ValueError(f"--configs {args.configs}: no {Path(v).name} there (the fitted "
                             "set: configs/paper000/)")
    print(f"jaxdea reproduce {args.paper}: size {args.size}, fitted set {args.configs}",
          flush=True)
    r = reproduce_paper000(out, configs=configs, size=args.size, root=".",
                           progress=not args.quiet)
    n = sum(r["claims"].values())
    print(f"claims met: {n} of {len(r['claims'])}"
          + (f" (not met: {', '.join(r['conflicts'])})" if r["conflicts"] else ""))
    for f in r["files"]:
        print(f"wrote {f}")
    print(f"done in {r['wall_s']:.0f} s")
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Add the ``reproduce`` command to ``sub``."""
    r = sub.add_parser("reproduce", help="regenerate a paper's study from the fitted "
                                         "parameter set (figures, claims table)")
    r.add_argument("paper", choices=PAPERS, help="which paper")
    r.add_argument("--out", required=True, help="output folder (new, empty, or an earlier "
                                                "reproduction)")
    r.add_argument("--configs", default="configs/paper000",
                   help="folder of the fitted configs (scdea_ls.toml, dcdea_rr.toml, "
                        "dcdea_ls.toml)")
    r.add_argument("--size", choices=["full", "small"], default="full",
                   help="map and peak-search size (small: a quick check)")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    r.set_defaults(func=_reproduce)
