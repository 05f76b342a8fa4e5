"""``jaxdea`` command line: ``jaxdea sweep|powermap|plot|rotary-study|calibrate|simulate|
optimise|reproduce ...`` (see ``jaxdea COMMAND --help``)."""

from __future__ import annotations

import argparse
import re
import sys
import warnings

from . import calibrate, maps, optimise, reproduce, rotary, simulate


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxdea`` parser with every command group's sub-commands."""
    from jaxdea import __version__

    p = argparse.ArgumentParser(prog="jaxdea", description=__doc__)
    p.add_argument("--version", action="version", version=f"jaxdea {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for group in (maps, rotary, calibrate, simulate, optimise, reproduce):
        group.add_parsers(sub)
    for command in sub.choices.values():  # every --help shows the defaults
        command.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``) and return the exit code: 0 on
    success, 2 with one line on stderr for a user error (bad argument, config, data or path),
    130 when interrupted."""
    args = build_parser().parse_args(_negative_values(sys.argv[1:] if argv is None else argv))
    from jaxdea._checks import JaxdeaError
    from jaxdea.engine.sharding import use_compile_cache, use_cpu_cores

    if argv is None:  # the command line (not a call from Python, whose JAX may be in use)
        # one JAX device per core: batched runs shard over all of them; multi-output fusion
        # where only the lane engine compiles (XLA aborts on some other programs)
        use_cpu_cores(fuse_outputs=args.command in ("sweep", "powermap"))
        use_compile_cache()  # a rerun on the same grid loads its compiled programs

    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line(warnings.showwarning)
            return args.func(args)
    except KeyboardInterrupt:
        print("\njaxdea: interrupted", file=sys.stderr)
        return 130
    except (JaxdeaError, ValueError, NotImplementedError, OSError) as exc:
        print(f"jaxdea: error: {exc}", file=sys.stderr)
        return 2


#: A value that starts with a minus sign: ``-1e-3``, ``-.5``, ``-2e-3:1e-3:5``, ``-inf``.
_NEGATIVE = re.compile(r"-(\d|\.\d|inf|nan)", re.IGNORECASE)


def _negative_values(argv: list[str]) -> list[str]:
    """``--mass -1e-3`` as ``--mass=-1e-3``: argparse takes a token that starts with ``-`` and
    is not a plain decimal (``-1e-3``, a range ``-1:1:5``) for an option, and would answer with
    its usage instead of the range check's one line."""
    out: list[str] = []
    for tok in argv:
        prev = out[-1] if out else ""
        if _NEGATIVE.match(tok) and prev.startswith("--") and "=" not in prev:
            out[-1] = f"{prev}={tok}"
        else:
            out.append(tok)
    return out


def _one_line(show):
    """``warnings.showwarning`` that prints jaxdea's :class:`~jaxdea.FieldWarning` and
    :class:`~jaxdea.studies.mapstore.PartWarning` as one line on stderr (other warnings as
    ``show`` does)."""
    from jaxdea._checks import FieldWarning
    from jaxdea.studies.mapstore import PartWarning

    def showwarning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, (FieldWarning, PartWarning)):
            print(f"jaxdea: warning: {message}", file=sys.stderr, flush=True)
        else:
            show(message, category, filename, lineno, file, line)

    return showwarning


if __name__ == "__main__":
    sys.exit(main())
