"""Config loading: the three reference configs load; bad values fail early, naming the field."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest

import jaxdea
from jaxdea.config import ConfigError, model_from_dict

CONFIGS = Path(__file__).parents[1] / "configs"


def raw(name: str = "dcdea_ls") -> dict:
    with (CONFIGS / f"{name}.toml").open("rb") as fh:
        return tomllib.load(fh)


@pytest.mark.parametrize("name", ["scdea_ls", "dcdea_rr", "dcdea_ls"])
def test_reference_configs_load(name):
    model = jaxdea.load_config(CONFIGS / f"{name}.toml")
    assert model.name == name
    assert float(model.voltage) == 4.9e3 and float(model.duty) == 0.5
    assert model.actuator.membrane.dielectric.mu_A.dtype == np.float64


def _set(cfg: dict, path: str, value):
    *head, last = path.split(".")
    node = cfg
    for k in head:
        node = node[k]
    node[last] = value
    return cfg


def _del(cfg: dict, path: str):
    *head, last = path.split(".")
    node = cfg
    for k in head:
        node = node[k]
    del node[last]
    return cfg


@pytest.mark.parametrize(
    "path, value, expected",
    [
        ("actuator.disk_mass", -1e-3, r"actuator\.disk_mass = -0\.001 .*\(0, inf\) kg"),
        ("membrane.outer_radius", 7.0e-3, r"membrane\.outer_radius .* greater than .*inner_radius"),
        ("membrane.outer_radius", 7.5e-3, r"membrane\.outer_radius .* greater than .*inner_radius"),
        ("membrane.dielectric.J_A", 0.0, r"membrane\.dielectric\.J_A = 0\.0 .*\(0, inf\)"),
        ("membrane.electrode.J_B", -3.0, r"membrane\.electrode\.J_B = -3\.0"),
        ("membrane.dielectric.tau", 0.0, r"membrane\.dielectric\.tau"),
        ("membrane.prestretch", 0.9, r"membrane\.prestretch = 0\.9 .*\[1, 10\]"),
        ("drive.duty", 1.0, r"drive\.duty = 1\.0 .*\(0, 1\)"),
        ("drive.voltage", float("nan"), r"drive\.voltage"),
        ("actuator.spring_stiffness", "stiff", r"actuator\.spring_stiffness must be a number"),
        # J above zero but below the stretch invariant at rest: the Gent spring is locked up
        ("membrane.dielectric.J_A", 0.5, r"membrane\.dielectric\.J_A is below the stretch"),
    ],
)
def test_bad_values_name_the_field_and_range(path, value, expected):
    cfg = _set(copy.deepcopy(raw()), path, value)
    with pytest.raises(ConfigError, match=expected):
        model_from_dict(cfg)


def test_unknown_and_missing_keys():
    with pytest.raises(ConfigError, match=r"unknown key\(s\) in \[actuator\]: stiffness"):
        model_from_dict(_set(copy.deepcopy(raw()), "actuator.stiffness", 600.0))
    with pytest.raises(ConfigError, match=r"missing key\(s\) in \[membrane\.dielectric\]: tau"):
        model_from_dict(_del(copy.deepcopy(raw()), "membrane.dielectric.tau"))
    with pytest.raises(ConfigError, match=r"missing key\(s\) in \[actuator\]: rod_length"):
        model_from_dict(_del(copy.deepcopy(raw("dcdea_rr")), "actuator.rod_length"))
    with pytest.raises(ConfigError, match=r"model = 'tricone' is not one of"):
        model_from_dict(_set(copy.deepcopy(raw()), "model", "tricone"))
    with pytest.raises(ConfigError, match=r"missing table\(s\): \[membrane\.electrode\]"):
        model_from_dict(_del(copy.deepcopy(raw()), "membrane.electrode"))


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        jaxdea.load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("model = \n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        jaxdea.load_config(bad)
