"""Loadings (drive + payload per cell) of a study's grid, built once for sweeps and maps."""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import ConfigError, FieldWarning, SweepError, check_choice, finite_array
from ..config.cones import parameter_range
from ..models.cone import Loading, Model
from ..params import parameter_names
from ..payloads import (
    Combined,
    Drag,
    Elastic,
    Gravity,
    LinearViscous,
    PayloadLaw,
    anchored,
    parameters,
    replace_parameters,
)
from ..signals import SquareWave

DRIVES = ("A", "B", "both")
#: The payload laws the cone studies take as ``payload=`` (and their sums).
PAYLOAD_LAWS = (LinearViscous, Drag, Elastic, Gravity, Combined)


def check_cone_model(model) -> None:
    """``model`` is a square-wave cone :class:`~jaxdea.models.Model` (what the cone studies
    run); else :class:`~jaxdea.ConfigError` saying what was given."""
    if isinstance(model, Model):
        return
    if isinstance(model, (str, bytes)) or hasattr(model, "__fspath__"):
        raise ConfigError(f"model must be a loaded model, got the path {model!r}: use "
                          "jaxdea.load_config(path) first")
    raise ConfigError("model must be a square-wave cone from jaxdea.load_config (model = "
                      f"scdea_ls, dcdea_rr or dcdea_ls), got {type(model).__name__}")


@eqx.filter_jit
def nominal_field(model: Model) -> jax.Array:
    """:meth:`Model.nominal_field` (largest nominal field ``voltage / H_m`` over the membranes
    at the zero-voltage static equilibrium, V/m; differentiable), compiled once per model
    structure: run eagerly, its Newton solve of the rest state costs ~0.4 s of dispatch."""
    return model.nominal_field()


def check_model_ranges(model: Model) -> None:
    """Every parameter of the cone ``model`` inside its config range: a model edited in code
    (:func:`jaxdea.params.set_params`, ``eqx.tree_at``) is refused as a config with that value
    would be (:class:`~jaxdea.ConfigError` naming the parameter), before any compute. Nothing
    is checked while the model is traced."""
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(model)):
        return
    for name, value in parameter_names(model).items():
        field = parameter_range(model, name)
        if field is not None:
            field.check(name, value)


def warn_breakdown(model: Model, stacklevel: int = 3) -> None:
    """Warn (:class:`~jaxdea.FieldWarning`) when ``model``'s nominal field (drive voltage over
    the dielectric's thickness at the zero-voltage rest state,
    :meth:`~jaxdea.Model.nominal_field`) exceeds its breakdown field (config key
    ``drive.breakdown_field``). Nothing is checked while the voltage is traced."""
    if isinstance(model.voltage, jax.core.Tracer):
        return
    field, limit = float(nominal_field(model)), float(model.breakdown_field)
    if field > limit:
        warnings.warn(FieldWarning(
            f"nominal field {field / 1e6:.4g} MV/m (drive.voltage {float(model.voltage):g} V "
            f"over the membrane's thickness at rest) is {field / limit:.3g}x the breakdown "
            f"field {limit / 1e6:g} MV/m (drive.breakdown_field): a real film would break "
            "down; the results are the model's only"), stacklevel=stacklevel)


def drive_pattern(model: Model, drive: str, phase: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-membrane amplitude multipliers and phases for a drive case.

    ``"A"``: membrane A only (the single cone's one membrane is "A"); ``"B"``: membrane B only;
    ``"both"``: A and B, B delayed by ``phase`` rad (0 = in-phase, pi = antiphase).
    """
    check_cone_model(model)
    names = model.actuator.membrane_names
    check_choice("drive", drive, DRIVES)
    if drive != "A" and len(names) == 1:
        raise SweepError(f"drive = {drive!r}: {model.name or 'this model'} has one membrane; "
                         "use drive='A'")
    if not math.isfinite(phase):
        raise SweepError(f"phase must be finite (allowed range [0, 2 pi)), got {phase!r}")
    if not 0.0 <= phase < 2.0 * math.pi:
        raise SweepError(f"phase = {phase!r} rad is outside the allowed range [0, 2 pi)")
    if drive != "both" and phase != 0.0:
        raise SweepError(f"phase = {phase!r} rad is only used with drive='both' (B delayed "
                         f"against A); got drive={drive!r}: drop phase or use drive='both'")
    on = np.array([drive in ("both", n) for n in names], dtype=float)
    phases = np.where(np.array(names) == "B", phase if drive == "both" else 0.0, 0.0)
    return on, phases


def payload_parameters(payload) -> dict[str, float]:
    """The law's name and parameters (SI), for a Dataset's attrs: ``{"payload": "Drag",
    "payload_linear": ..., ...}`` (a sum: ``"Drag + Gravity"``; the mass is recorded
    separately, as ``mass``; an axis parameter is left out: it is a coordinate)."""
    out: dict = {"payload": " + ".join(type(law).__name__ for law in payload.laws)}
    for name, value in parameters(payload).items():
        if value is not None and np.ndim(value) == 0:
            out[f"payload_{name}"] = float(np.asarray(value))
    return out


def check_payload(mass, damping, payload, axes: bool = False):
    """Validate the payload of a cone study, before any compute.

    **Arguments:**

    - `mass`: payload mass, kg, or ``None`` to take the payload law's own ``mass``.
    - `damping`: the linear dashpot's ``c`` (N s/m), shorthand for
      :class:`~jaxdea.LinearViscous`; ``None`` when `payload` is given.
    - `payload`: a payload law (:data:`PAYLOAD_LAWS`, or a sum of them) or ``None``.
    - `axes`: whether one law parameter may be a 1-D axis (a power map's second axis).

    **Returns:**

    ``(mass, damping, payload)``: the mass as a float array; `damping` as a float array or
    ``None``; the law with its mass set to ``mass`` (scalar parameters), or ``None``.
    Raises :class:`~jaxdea.SweepError` naming the offending field.
    """
    if payload is None:
        if damping is None:
            raise SweepError("damping is missing: give damping (N s/m, the linear viscous "
                             "payload) or payload=<a payload law, e.g. jaxdea.Drag(...)>")
        if mass is None:
            raise SweepError("mass is missing: give the payload mass (kg, >= 0)")
        return (finite_array("mass", mass, nonnegative=True),
                finite_array("damping", damping, nonnegative=True), None)
    if damping is not None:
        raise SweepError("give damping (shorthand for jaxdea.LinearViscous) or payload, not "
                         "both: put the damping into the payload law")
    if not isinstance(payload, PAYLOAD_LAWS):
        raise SweepError("payload must be a payload law ("
                         + ", ".join(f"jaxdea.{c.__name__}" for c in PAYLOAD_LAWS[:-1])
                         + f", or a sum of them with +), got {type(payload).__name__}")
    axis_names = []
    for law in payload.laws:
        for f in dataclasses.fields(law):
            value = getattr(law, f.name)
            where = f"payload.{f.name}" if len(payload.laws) == 1 else (
                f"payload {type(law).__name__}.{f.name}")
            if (value is None and f.name == "anchor") or isinstance(value, jax.core.Tracer):
                continue  # unset anchor (set by the study); traced (fits, gradients)
            is_axis = axes and f.name != "mass" and np.ndim(value) == 1
            if is_axis:
                axis_names.append(f.name)
            if np.ndim(value) != 0 and not is_axis:
                raise SweepError(f"{where} must be a scalar, got shape {np.shape(value)}"
                                 + (" (a power map takes one law parameter as a 1-D axis)"
                                    if axes else " (use powermap for an axis)"))
            finite_array(where, value, nonnegative=f.name not in law.signed_fields,
                         positive=f.name in law.positive_fields)
    if len(axis_names) > 1:
        raise SweepError("payload: at most one law parameter may be an axis (1-D array), got "
                         f"{', '.join(axis_names)} (the CLI's --damping is the law's linear)")
    if isinstance(payload.mass, jax.core.Tracer):
        return finite_array("mass", mass, nonnegative=True), None, payload
    law_mass = float(np.asarray(payload.mass))
    if mass is None:
        mass = law_mass
    mass = finite_array("mass", mass, nonnegative=True)
    if np.any(mass != law_mass) and law_mass != 0.0:
        raise SweepError(f"mass = {mass.tolist()} kg differs from payload.mass = {law_mass:g} "
                         "kg: give the payload mass once (drop mass=, or make them equal)")
    return mass, None, payload


def cell_payload(payload, mass, n: int, **values):
    """``payload`` (scalar parameters) for ``n`` cells with masses ``mass`` ``(n,)``, kg, and
    any law parameter given in ``values`` as an ``(n,)`` array."""
    cells = jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(jnp.asarray(a, dtype=float), (n,)),
        replace_parameters(payload, **{k: 0.0 for k in values}) if values else payload)
    if values:
        cells = replace_parameters(cells, **{k: jnp.asarray(v, dtype=float)
                                             for k, v in values.items()})
    return cells.with_mass(jnp.asarray(mass))


@eqx.filter_jit
def _rest_position(actuator) -> jax.Array:
    return actuator.rest_position()


def anchor_payload(model: Model, payload):
    """``payload`` with an :class:`~jaxdea.Elastic` law's unset anchor at the actuator's rest
    position without payload (m; traced when the model is)."""
    if payload is None or "anchor" not in parameters(payload) or parameters(
            payload)["anchor"] is not None:
        return payload
    # a jax scalar, not a float: inside a transformation (a fit, a gradient) it is traced
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(model))
    return anchored(payload, model.actuator.rest_position() if traced
                    else _rest_position(model.actuator))


def cell_loadings(amplitude, frequency, duty, phase, mass, damping, payload=None,
                  **values) -> Loading:
    """Loadings of ``n`` cells from per-cell arrays: ``amplitude`` and ``phase`` ``(n,
    n_membranes)`` (V, rad), ``frequency``, ``mass``, ``damping`` ``(n,)`` (Hz, kg, N s/m),
    ``duty`` a scalar. With a payload law ``payload`` (checked, scalar parameters),
    ``damping`` is ignored and every cell gets that law with its ``mass`` and the per-cell
    law parameters ``values`` (``(n,)`` arrays, e.g. ``quadratic=...``)."""
    n = np.shape(frequency)[0]
    return Loading(
        drive=SquareWave(
            amplitude=jnp.asarray(amplitude),
            frequency=jnp.asarray(frequency),
            # float, not weak: a map's duty (a Python float) and a sweep's (the model's
            # array) then give the same program
            duty=jnp.broadcast_to(jnp.asarray(duty, dtype=float), (n,)),
            phase=jnp.asarray(phase),
        ),
        payload=(LinearViscous(mass=jnp.asarray(mass), damping=jnp.asarray(damping))
                 if payload is None else cell_payload(payload, mass, n, **values)),
    )


@eqx.filter_jit
def _rest_checks(actuator, payload):
    """Per cell: (payload position at rest, smallest Gent margin at rest) with ``payload``
    (leaves ``(n,)``) on."""
    def one(law):
        y = actuator.initial_state(law)
        return y.q[actuator.payload_dof], actuator.lockup_margin(y)

    return jax.vmap(one)(payload)


def check_rest(model: Model, payload) -> None:
    """:class:`~jaxdea.SweepError` when a payload that loads the disk at rest (a weight, a
    preloaded spring; ``payload`` with leaves ``(n,)``) leaves the actuator no static
    equilibrium: the Newton solve diverges or a membrane is locked up (Gent limit) at rest.
    Nothing is checked for other payloads or while the model is traced."""
    if payload is None or not payload.loads_at_rest or any(
            isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((model, payload))):
        return
    x, margin = (np.asarray(a) for a in _rest_checks(model.actuator, payload))
    bad = ~(np.isfinite(x) & np.isfinite(margin) & (margin > 0))
    if bad.any():
        i = int(np.argmax(bad))
        load = float(np.asarray(payload.force(x[i] if np.isfinite(x[i]) else 0.0, 0.0))[i])
        raise SweepError(
            f"payload: the actuator has no static equilibrium with this payload at rest "
            f"({int(bad.sum())} of {bad.size} cells; e.g. mass {float(payload.mass[i]):g} kg, "
            f"force at rest {load:.4g} N against +x): the membrane locks up or the load "
            "exceeds what it can hold; lower the weight (mass, Gravity.tilt) or the spring's "
            "preload")


def make_loadings(model: Model, mass, damping, freq, drive: str = "A",
                  phase: float = 0.0, payload=None) -> Loading:
    """Loadings (drive and payload per cell) of a cone model.

    **Arguments:**

    - `model`: a square-wave cone from :func:`jaxdea.load_config` (its voltage and duty may
      be traced).
    - `mass`, `damping`, `freq`: payload mass (kg, >= 0), damping (N s/m, >= 0) and drive
      frequency (Hz, > 0), broadcast against each other.
    - `drive`: ``"A"``, ``"B"`` or ``"both"``; `phase`: B's delay with ``"both"``, rad.
    - `payload`: a payload law (:class:`~jaxdea.Drag`, :class:`~jaxdea.Elastic`,
      :class:`~jaxdea.Gravity`, ... or a sum of them) with scalar parameters, instead of
      `damping` (then ``damping=None``; `mass` may be ``None`` to use the law's mass).
      ``damping=c`` is the shorthand for ``LinearViscous``. An :class:`~jaxdea.Elastic`
      law without ``anchor`` is anchored at the actuator's rest position.

    **Returns:**

    A :class:`~jaxdea.Loading` whose leaves have the broadcast's cells (flattened, C order)
    as their leading axis.
    """
    mass, damping, payload = check_payload(mass, damping, payload)
    payload = anchor_payload(model, payload)
    freq = finite_array("freq", freq, positive=True)
    on, phases = drive_pattern(model, drive, float(phase))
    m, c, f = (a.ravel() for a in np.broadcast_arrays(
        mass, 0.0 if damping is None else damping, freq))
    n = f.size
    # jnp arithmetic on the model's voltage and duty: they may be traced (calibration)
    if payload is not None:  # the loaded rest exists: once per distinct mass, not per cell
        masses = np.unique(m)
        check_rest(model, cell_payload(payload, masses, masses.size))
    amp = jnp.broadcast_to(jnp.asarray(on)[None, :] * model.voltage, (n, on.size))
    return cell_loadings(amp, f, model.duty, jnp.broadcast_to(jnp.asarray(phases), (n, on.size)),
                         m, c, payload)


@dataclass
class Grid:
    """A validated (M, c, f[, phase]) grid and its drive: builds the loadings of any range of
    flat (C-order) cell indices, the same values as :func:`make_loadings`. With a payload law
    the second axis is one of its parameters (``law_axis``, e.g. ``"quadratic"``) instead of
    the linear dashpot's ``c``."""

    axes: dict  # name -> 1-D numpy axis, in output order
    shape: tuple
    amplitude: np.ndarray  # (n_phase, n_membranes), V
    phases: np.ndarray  # (n_phase, n_membranes), rad
    duty: float
    payload: PayloadLaw | None = None  # anchored; law_axis's parameter is the axis
    law_axis: str = "c"

    def loadings(self, idx: np.ndarray) -> Loading:
        """Loadings of flat (C-order) cells ``idx``."""
        full = self.shape if len(self.shape) == 4 else self.shape + (1,)
        im, ic, jf, jp = np.unravel_index(idx, full)
        second = self.axes[self.law_axis][ic]
        if self.payload is None:
            return cell_loadings(self.amplitude[jp], self.axes["f"][jf], self.duty,
                                 self.phases[jp], self.axes["M"][im], second)
        return cell_loadings(self.amplitude[jp], self.axes["f"][jf], self.duty,
                             self.phases[jp], self.axes["M"][im], 0.0, self.payload,
                             **{self.law_axis: second})
