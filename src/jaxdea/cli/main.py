"""``jaxdea`` command line: ``jaxdea sweep|powermap|plot|rotary-study|calibrate|simulate ...``
(see ``jaxdea COMMAND --help``)."""

from __future__ import annotations

import argparse
import sys

from . import calibrate, maps, rotary, simulate


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxdea`` parser with every command group's sub-commands."""
    p = argparse.ArgumentParser(prog="jaxdea", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    for group in (maps, rotary, calibrate, simulate):
        group.add_parsers(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxdea._checks import JaxdeaError
    from jaxdea.engine.sharding import use_cpu_cores

    if argv is None:  # the command line (not a call from Python, whose JAX may be in use)
        use_cpu_cores()  # one JAX device per core: batched runs shard over all of them

    try:
        return args.func(args)
    except (JaxdeaError, ValueError, NotImplementedError) as exc:
        print(f"jaxdea: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
