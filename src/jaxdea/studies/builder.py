"""``theta -> (actuator, loadings)``: the designs of the design studies as functions of named
parameters (model paths of :mod:`jaxdea.params`, the payload's mass and damping, the drive
frequency, and a payload law's parameters ``"payload.<name>"``)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import CalibrationError, ConfigError, SweepError, finite_array
from ..config.cones import parameter_range
from ..config.fields import Field
from ..models.cone import Model
from ..params import make_params, resolve_names, with_theta
from ..payloads import PayloadLaw, parameters, replace_parameters
from .loadings import anchor_payload, cell_loadings, check_cone_model, check_payload, drive_pattern

#: Names of the payload and drive values that can be differentiated besides model paths
#: (and ``"payload.<name>"`` for a parameter of a payload law).
PAYLOAD_NAMES = ("mass", "damping", "freq")
#: Prefix of a payload law's parameters in ``vary`` / ``values``.
LAW = "payload."


def _is_payload(name: str) -> bool:
    return name in PAYLOAD_NAMES or name.startswith(LAW)


class Builder(eqx.Module):
    """``theta -> (actuator, loadings)`` of one design over a batch of cells.

    ``theta`` holds the model parameters ``params`` (in order), then the payload and drive
    values named in ``slots`` (positions in ``theta``, -1 = not varied) and the payload law's
    parameters ``law_fields`` at ``law_slots``, then, if ``shift >= 0``, a frequency shift
    added to every cell's frequency. Without a payload law (``payload=None``) the payload is
    the linear dashpot ``damping``.
    """

    model: Model
    params: tuple = eqx.field(static=True)
    slots: tuple = eqx.field(static=True)  # theta positions of mass, damping, freq (-1: none)
    shift: int = eqx.field(static=True)
    mass: jax.Array
    damping: jax.Array
    freq: jax.Array
    on: jax.Array
    phases: jax.Array
    payload: PayloadLaw | None = None  # scalar parameters; its mass is ``mass``
    law_fields: tuple = eqx.field(static=True, default=())
    law_slots: tuple = eqx.field(static=True, default=())

    def __call__(self, theta):
        model = with_theta(self.model, list(self.params), theta[:len(self.params)])
        n = self.freq.shape[0]
        m, c, f = (self.mass, self.damping, self.freq)
        im, ic, jf = self.slots
        m = m if im < 0 else jnp.broadcast_to(theta[im], (n,))
        c = c if ic < 0 else jnp.broadcast_to(theta[ic], (n,))
        f = f if jf < 0 else jnp.broadcast_to(theta[jf], (n,))
        if self.shift >= 0:
            f = f + theta[self.shift]
        amp = jnp.broadcast_to(self.on * model.voltage, (n, self.on.shape[0]))
        ph = jnp.broadcast_to(self.phases, (n, self.on.shape[0]))
        if self.payload is None:
            return model.actuator, cell_loadings(amp, f, model.duty, ph, m, c)
        law = replace_parameters(self.payload, **{
            k: theta[i] for k, i in zip(self.law_fields, self.law_slots)})
        law = anchor_payload(model, law)  # an Elastic anchor follows the design's rest
        return model.actuator, cell_loadings(amp, f, model.duty, ph, m, 0.0, law)


def resolve(model: Model, names, payload: PayloadLaw | None = None) -> dict[str, str]:
    """Validated names: ``{given name: full model path or payload name}``, in the order given.

    **Arguments:**

    - `model`: a cone :class:`~jaxdea.Model`.
    - `names`: parameter names (model paths or suffixes, :data:`PAYLOAD_NAMES`, or
      ``"payload.<name>"`` for a parameter of `payload`).
    - `payload`: the payload law, if any.

    **Returns:**

    The mapping; :class:`~jaxdea.SweepError` for an unknown, ambiguous or repeated name.
    """
    names = list(names)
    law = {} if payload is None else parameters(payload)
    for n in names:
        if n.startswith(LAW) and n[len(LAW):] not in law:
            raise SweepError(
                f"{n!r}: " + ("no payload law is given (payload=...)" if payload is None else
                              f"the payload has no parameter {n[len(LAW):]!r}; it has "
                              + ", ".join(LAW + k for k in law)))
    if payload is not None and "damping" in names:
        raise SweepError("'damping' is the linear dashpot's; with a payload law vary "
                         "'payload.linear' instead")
    rest = [n for n in names if not _is_payload(n)]
    try:
        full = resolve_names(model, rest) if rest else []
    except CalibrationError as e:
        raise SweepError(str(e).replace(" in fit", " in vary")) from None
    to_full = dict(zip(rest, full))
    return {n: to_full.get(n, n) for n in names}


#: The allowed ranges of the payload's and the drive's names (as the sweeps check them).
PAYLOAD_RANGES = {"mass": Field(0.0, np.inf, unit="kg"),
                  "damping": Field(0.0, np.inf, unit="N s/m"),
                  "freq": Field(0.0, np.inf, lo_open=True, unit="Hz")}


def check_values(model: Model, mapping: dict, values: dict, what: str = "") -> None:
    """Every concrete value of ``values`` (``{given name: scalar or array}``; ``mapping`` from
    :func:`resolve`) inside its parameter's allowed range (the config's, or
    :data:`PAYLOAD_RANGES`), checked before any compute: a design with a negative spring or
    a prestretch below 1 is refused, not solved. Traced values (under ``jax.grad``) pass.
    ``what``: how the message names a value, ``"vary"`` gives ``vary['name']``."""
    for given, value in values.items():
        if isinstance(value, jax.core.Tracer):
            continue
        full = mapping[given]
        field = PAYLOAD_RANGES.get(full) if _is_payload(full) else parameter_range(model, full)
        label = f"{what}[{given!r}]" if what else given
        arr = finite_array(label, value)
        if field is None:
            continue
        for v in arr.ravel():
            try:
                field.check(label, float(v))
            except ConfigError as e:
                raise SweepError(str(e)) from None


def split_names(mapping: dict) -> tuple[list[str], list[str], list[str]]:
    """(given names in theta order, model paths, payload names): model paths first."""
    model_keys = [k for k, v in mapping.items() if not _is_payload(v)]
    pay_keys = [k for k, v in mapping.items() if _is_payload(v)]
    return (model_keys + pay_keys, [mapping[k] for k in model_keys],
            [mapping[k] for k in pay_keys])


def make_builder(model, full, pay, *, mass, damping, freq, drive, phase, shift, payload=None):
    """The :class:`Builder` of ``model`` with model paths ``full`` and payload names ``pay``
    varied (in that order in ``theta``), over the cells of ``freq``; ``payload``: a payload
    law instead of the linear dashpot ``damping`` (its mass: ``mass``, or its own)."""
    check_cone_model(model)
    on, phases = drive_pattern(model, drive, 0.0 if phase is None else float(phase))
    params = tuple(make_params(model, full, transforms={n: "linear" for n in full})
                   if full else ())  # none varied: the model as it is
    pos = {n: len(full) + i for i, n in enumerate(pay)}
    slots = tuple(pos.get(k, -1) for k in PAYLOAD_NAMES)
    if payload is not None:
        mass_arr, _, payload = check_payload(None if "mass" in pay else mass, damping, payload)
        mass = float(mass_arr[0])
        payload = payload.with_mass(0.0)  # the cells' mass is the builder's
    for name, v in (("mass", mass), ("damping", damping)):
        if name not in pay and v is None and not (name == "damping" and payload is not None):
            raise SweepError(f"{name} is needed (allowed range [0, inf)), got None")
    f = np.atleast_1d(np.asarray(freq, float))
    n = f.size
    mass = 0.0 if mass is None else float(finite_array("mass", mass, nonnegative=True)[0])
    damping = 0.0 if damping is None else float(
        finite_array("damping", damping, nonnegative=True)[0])
    law = [k for k in pay if k.startswith(LAW)]
    return Builder(model=model, params=params, slots=slots,
                   shift=len(full) + len(pay) if shift else -1,
                   mass=jnp.full(n, mass), damping=jnp.full(n, damping), freq=jnp.asarray(f),
                   on=jnp.asarray(on), phases=jnp.asarray(phases), payload=payload,
                   law_fields=tuple(k[len(LAW):] for k in law),
                   law_slots=tuple(pos[k] for k in law))


def law_value(payload: PayloadLaw | None, name: str) -> float:
    """The current value of ``"payload.<name>"`` of ``payload``."""
    return float(np.asarray(parameters(payload)[name[len(LAW):]]))


def theta_of(values: dict, keys: list):
    """``values`` in ``keys`` order as a float64 vector."""
    if not keys:
        return jnp.zeros(0)
    return jnp.stack([jnp.asarray(values[k], dtype=jnp.float64).reshape(()) for k in keys])
