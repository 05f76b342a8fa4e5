"""Payload flags of ``jaxdea sweep`` and ``jaxdea powermap``: the payload law from the config's
``[payload]`` table and the command line (:mod:`jaxdea.payloads`)."""

from __future__ import annotations

import argparse

import numpy as np

from .args import parse_points

#: flag -> (law, parameter, help). A flag given makes its law part of the payload.
FLAGS = {
    "quadratic": ("Drag", "quadratic", "quadratic drag c2 of f = c v + c2 v|v|, N s^2/m^2"),
    "coulomb": ("Drag", "coulomb", "Coulomb friction force F_c (smoothed: F_c tanh(v / v_s)), N"),
    "coulomb_velocity": ("Drag", "coulomb_velocity", "Coulomb smoothing velocity v_s, m/s "
                         "(default 1e-3)"),
    "load_stiffness": ("Elastic", "stiffness", "stiffness k_p of a spring from the payload to "
                       "ground, N/m (relaxed at the actuator's rest unless preloaded)"),
    "load_preload": ("Elastic", "preload", "that spring's force against +x at the actuator's "
                     "rest, N"),
    "tilt": ("Gravity", "tilt", "add the payload's weight: mounting tilt, rad (0: the payload "
             "hangs below the actuator, pi: sits on top, pi/2: horizontal)"),
}


def add_payload_args(p: argparse.ArgumentParser, ranges: bool) -> None:
    """The payload-law flags; with ``ranges`` each also takes MIN:MAX:N[:log|:lin] (one of
    them, or --damping, may be a map axis)."""
    g = p.add_argument_group(
        "payload law (jaxdea.Drag + Elastic + Gravity; default: the config's [payload] table, "
        "else the linear dashpot --damping)"
        + ("; one flag may be MIN:MAX:N[:log|:lin], the map's second axis (a range from a "
           "negative value needs '=': --tilt=-1:1:5:lin)" if ranges else ""))
    for name, (_, _, text) in FLAGS.items():
        g.add_argument("--" + name.replace("_", "-"), dest=name,
                       type=str if ranges else float, help=text)


def _value(text, flag: str, ranges: bool):
    if not ranges or isinstance(text, float):
        return float(text)
    if ":" in str(text):
        return parse_points(str(text), flag)
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{flag} must be a number or MIN:MAX:N[:log|:lin], got {text!r}") \
            from None


def cli_payload(args, ranges: bool = False):
    """``(payload law or None, damping)`` of the command: the config's ``[payload]`` table
    with the flags applied (``--damping`` becomes the law's ``linear``). ``None`` and the
    plain ``--damping`` when neither a table nor a law flag is given."""
    import jaxdea
    from jaxdea.payloads import Drag, Elastic, Gravity, parameters, replace_parameters

    given = {k: getattr(args, k) for k in FLAGS if getattr(args, k, None) is not None}
    table = jaxdea.load_payload(args.config)
    damping = args.damping
    if not given and (table is None or damping is not None):
        return None, damping
    law = table if table is not None else Drag(0.0)
    if ranges or getattr(args, "mass", None) is not None:
        law = law.with_mass(0.0)  # --mass (a map's M axis) overrides the table's mass
    values = {"linear": _value(damping, "--damping", ranges)} if damping is not None else {}
    kinds = {type(x).__name__ for x in law.laws}
    for name, text in given.items():
        kind, field, _ = FLAGS[name]
        if kind not in kinds:
            law = law + {"Elastic": Elastic, "Gravity": Gravity}[kind]()
            kinds.add(kind)
        values[field] = _value(text, "--" + name.replace("_", "-"), ranges)
    if "linear" in values and "linear" not in parameters(law):
        raise ValueError("--damping with a payload law needs a Drag in it")
    return replace_parameters(law, **values), None


def describe(payload, damping) -> str:
    """One line naming the payload law for the command's banner."""
    if payload is None:
        return "linear dashpot"
    vals = ", ".join(f"{k} {np.asarray(v).size} values" if np.ndim(v) else f"{k}={float(v):g}"
                     for k, v in _params(payload).items())
    return " + ".join(type(x).__name__ for x in payload.laws) + f" ({vals})"


def _params(payload) -> dict:
    from jaxdea.payloads import parameters

    return {k: v for k, v in parameters(payload).items() if v is not None}
