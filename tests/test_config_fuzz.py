"""Property-based tests: any options file ends in FilterOptions or ConfigError.

Random bytes, random YAML/TOML documents (valid syntax with random keys and values of
every type, including NaN, huge numbers, nested tables and lists), and valid keys with
random values: loading must never raise anything but the package's ConfigError (no
uncaught exception, no hang).
"""

from __future__ import annotations

import json
import math

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vislam.core.options import FLAT_FIELDS, OPTION_GROUPS, FilterOptions
from vislam.errors import ConfigError
from vislam.tools.config import resolve_options

FIELDS = list(FLAT_FIELDS)  # the flat names (FilterOptions' own dataclass fields are its groups)
#: (group, field name in the group) of every option, for nested documents.
NESTED = sorted(FLAT_FIELDS.values())
SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=3)),
                      max_leaves=6)
keys = st.one_of(st.sampled_from(FIELDS), st.text(min_size=1, max_size=12))


def _resolve(path):
    try:
        opts = resolve_options(path)
    except ConfigError as exc:
        assert str(path) in str(exc) or path.name in str(exc)
        assert "\n" not in str(exc)
        return None
    assert isinstance(opts, FilterOptions)
    return opts


@SETTINGS
@given(data=st.binary(max_size=200), suffix=st.sampled_from([".yaml", ".yml", ".toml"]))
def test_random_bytes(tmp_path, data, suffix):
    path = tmp_path / f"options{suffix}"
    path.write_bytes(data)
    _resolve(path)


@SETTINGS
@given(doc=st.dictionaries(keys, values, max_size=5))
def test_random_yaml_documents(tmp_path, doc):
    path = tmp_path / "options.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    opts = _resolve(path)
    if opts is not None:
        # anything accepted is a valid, finite set of options that round-trips
        assert FilterOptions.from_dict(opts.to_dict()) == opts
        for k, v in opts.to_dict().items():
            if isinstance(v, float):
                assert math.isfinite(v), k


def _toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and math.isnan(v):
            return "nan"
        if isinstance(v, float) and math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    return json.dumps(str(v))


@SETTINGS
@given(doc=st.dictionaries(st.sampled_from(FIELDS), st.one_of(st.booleans(), st.integers(-(10**6), 10**6),
                                                             st.floats(allow_nan=True), st.text(max_size=10)),
                           max_size=6))
def test_valid_keys_random_toml_values(tmp_path, doc):
    path = tmp_path / "options.toml"
    path.write_text("".join(f"{k} = {_toml_value(v)}\n" for k, v in doc.items()), encoding="utf-8")
    _resolve(path)


@SETTINGS
@given(items=st.lists(st.tuples(st.sampled_from(NESTED), values), max_size=5),
       extra=st.dictionaries(st.sampled_from(list(OPTION_GROUPS)), values, max_size=1))
def test_nested_documents_random_values(tmp_path, items, extra):
    """Groups of options with random values (and now and then a group given a random
    non-mapping value): FilterOptions or a one-line ConfigError, as flat documents."""
    doc: dict = {}
    for (group, name), value in items:
        doc.setdefault(group, {})[name] = value
    for group, value in extra.items():
        doc.setdefault(group, value)
    path = tmp_path / "options.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    opts = _resolve(path)
    if opts is not None:
        assert FilterOptions.from_dict(opts.to_nested_dict()) == opts == FilterOptions.from_dict(opts.to_dict())


@pytest.mark.parametrize("text", [
    "velocity_noise_mps: .nan\n",
    "pixel_noise_px: 1e400\n",
    "gating_probability: 1.0\n",
    "ekf: [oc]\n",
    "max_consecutive_gated: 2.5\n",
    "- a list\n",
    "velocity_noise_mps: {nested: 1}\n",
    "noise: {velocity_mps: .nan}\n",
    "noise: 1\n",
    "noise: {velocity_mps: 0.5}\nvelocity_noise_mps: 0.5\n",
    "velocity_noise_mps: 0.5\nvelocity_noise_mps: 0.6\n",
])
def test_known_bad_yaml(tmp_path, text):
    path = tmp_path / "bad.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError):
        resolve_options(path)
