"""FilterOptions by component: every flat name maps to one nested field and back, the
nested and flat spellings of an options file give equal options, validation comes from
the fields' metadata, and flat access, keywords and replace keep working."""

from __future__ import annotations

import dataclasses

import pytest
import yaml

from vislam.core.options import (FLAT_FIELDS, KINDS, OPTION_GROUPS, FilterOptions, NoiseOptions, check_value,
                                 flatten_options, nest_options)
from vislam.errors import ConfigError
from vislam.tools.config import load_options_file, resolve_options

#: A value other than the default for each flat name (valid, of the field's kind).
CHANGED = {
    "velocity_noise_mps": (0.4, 0.5, 0.6), "angular_noise_radps": 0.05, "pixel_noise_px": 1.5,
    "initial_position_std_m": 0.1, "initial_rotation_std_rad": 0.01, "min_disparity_px": 1.0, "max_depth_m": 60.0,
    "min_depth_m": 1.0, "max_row_difference_px": 2.0, "init_frames": 2, "probation_frames": 2,
    "landmark_parametrization": "cartesian", "keep_all_landmarks": True, "max_landmarks_in_state": 400, "landmark_motion": True,
    "landmark_velocity_std_mps": 1.0, "landmark_acceleration_std_mps2": 0.5, "gating_probability": None,
    "max_consecutive_gated": 5, "drift_test_probability": 0.9, "ekf": "standard", "update_iterations": 2,
    "update_iteration_tolerance": 0.0, "repeated_observations": "split", "stalled_tracks": "keep",
    "stall_max_delay_frames": 4, "imu_bias_sigma_mps": 0.3, "imu_bias_sigma_radps": (0.001, 0.002, 0.003),
    "imu_bias_time_constant_s": 20.0, "velocity_frame": "body", "level_velocity_jacobian": False,
    "gyro_bias_radps": (0.001, 0.0, -0.001), "velocity_bias_mps": (0.1, 0.0, 0.0), "velocity_scale": 1.05,
    "timestamp_scale": 0.001, "imu_camera_rotation_correction_deg": (0.5, 0.0, 0.0),
    "cam_T_imu": ((0.0, -1.0, 0.0, 0.1), (0.0, 0.0, -1.0, 0.2), (1.0, 0.0, 0.0, 0.3), (0.0, 0.0, 0.0, 1.0)),
    "velocity_association": "current", "time_offset_s": -0.02, "smoother_window_s": 1.0,
    "smoother_pixel_noise_px": None, "smoother_kernel": "huber", "smoother_kernel_scale": 3.0,
    "smoother_relinearize_threshold": 0.05, "smoother_landmark_prior_m": 10.0, "smoother_outlier_sigma": 0.0,
    "smoother_drift_ratio": None, "smoother_drift_min_speed_mps": 1.0, "smoother_pose_covariance": True,
    "refine": True, "refine_kernel": "cauchy", "refine_kernel_scale": 2.0, "refine_outlier_px": 4.0,
    "refine_max_iterations": 20,
}


def test_every_flat_name_maps_to_exactly_one_nested_field():
    nested = [(g, f.name) for g, cls in OPTION_GROUPS.items() for f in dataclasses.fields(cls)]
    assert len(nested) == len(set(nested)) == len(FLAT_FIELDS) == 54
    assert sorted(FLAT_FIELDS.values()) == sorted(nested)  # a bijection flat <-> (group, field)
    assert set(FilterOptions().to_dict()) == set(FLAT_FIELDS)
    assert set(CHANGED) == set(FLAT_FIELDS)
    for flat, (group, name) in FLAT_FIELDS.items():
        opts = FilterOptions(**{flat: CHANGED[flat]})
        assert getattr(getattr(opts, group), name) == CHANGED[flat] == getattr(opts, flat)
        # only that field differs from the defaults
        diff = {k for k, v in opts.to_dict().items() if v != FilterOptions().to_dict()[k]}
        assert diff == {flat}


def test_flat_nested_flat_round_trip():
    flat = FilterOptions(**CHANGED).to_dict()
    nested = nest_options(flat)
    assert list(nested) == list(OPTION_GROUPS)
    assert flatten_options(nested) == flat
    opts = FilterOptions(**CHANGED)
    assert opts.to_nested_dict() == nested
    assert FilterOptions.from_dict(nested) == FilterOptions.from_dict(flat) == opts
    for group in OPTION_GROUPS:  # the groups of the nested mapping are the groups' fields
        assert getattr(opts, group) == OPTION_GROUPS[group](**{k: v for k, v in getattr(opts, group).__dict__.items()})


def test_nested_and_flat_files_give_equal_options(tmp_path):
    flat_yaml = tmp_path / "flat.yaml"
    flat_yaml.write_text("velocity_noise_mps: 0.5\nangular_noise_radps: 0.05\ngating_probability: null\n"
                         "smoother_window_s: 1\nrefine: true\nrefine_kernel: cauchy\n")
    nested_yaml = tmp_path / "nested.yaml"
    nested_yaml.write_text("noise:\n  velocity_mps: 0.5\n  angular_radps: 0.05\ngating:\n  probability: null\n"
                           "smoother:\n  window_s: 1\nrefinement: {enabled: true, kernel: cauchy}\n")
    nested_toml = tmp_path / "nested.toml"
    nested_toml.write_text('[noise]\nvelocity_mps = 0.5\nangular_radps = 0.05\n[gating]\nprobability = "none"\n'
                           '[smoother]\nwindow_s = 1\n[refinement]\nenabled = true\nkernel = "cauchy"\n')
    mixed_toml = tmp_path / "mixed.toml"
    mixed_toml.write_text('velocity_noise_mps = 0.5\ngating_probability = false\nrefine = true\n[noise]\n'
                          'angular_radps = 0.05\n[smoother]\nwindow_s = 1.0\n[refinement]\nkernel = "cauchy"\n')
    options = [resolve_options(p) for p in (flat_yaml, nested_yaml, nested_toml, mixed_toml)]
    assert all(o == options[0] for o in options)
    assert options[0].velocity_noise_mps == 0.5 and options[0].gating_probability is None
    assert options[0].smoother_window_s == 1.0 and isinstance(options[0].smoother_window_s, float)
    assert load_options_file(nested_yaml) == load_options_file(flat_yaml)
    # a flag still overrides a nested file, under its flat name
    assert resolve_options(nested_yaml, {"velocity_noise_mps": 0.7}).noise.velocity_mps == 0.7
    # the flat dump of nested options reloads equal (the shape of summary.json and suggested.yaml)
    dump = tmp_path / "dump.yaml"
    dump.write_text(yaml.safe_dump(options[0].to_dict()))
    assert resolve_options(dump) == options[0]
    nested_dump = tmp_path / "nested_dump.yaml"
    nested_dump.write_text(yaml.safe_dump(options[0].to_nested_dict()))
    assert resolve_options(nested_dump) == options[0]


@pytest.mark.parametrize("text, words", [
    ("noise:\n  velocty_mps: 0.5\n", ["group 'noise'", "'velocty_mps'", "did you mean 'velocity_mps'"]),
    ("nosie:\n  velocity_mps: 0.5\n", ["'nosie'", "did you mean 'noise'"]),
    ("noise: 0.5\n", ["'noise'", "group", "mapping"]),
    ("velocity_noise_mps: 0.5\nnoise:\n  velocity_mps: 0.6\n", ["noise.velocity_mps", "twice"]),
    ("gating:\n  probability: 1.5\n", ["gating_probability", "(0, 1)"]),
    ("smoother:\n  kernel: fancy\n", ["smoother_kernel", "fancy"]),
    ("filter:\n  velocity_noise_mps: 0.5\n", ["'filter'", "table"]),
    ("window_s: 1.0\n", ["'window_s'", "'smoother_window_s'", "group 'smoother'"]),
])
def test_nested_key_errors_are_one_line_with_did_you_mean(tmp_path, text, words):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        resolve_options(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message
    for word in words:
        assert word in message


def test_keywords_replace_and_groups():
    opts = FilterOptions(velocity_noise_mps=0.5, smoother_window_s=1.0)
    assert opts.noise.velocity_mps == 0.5 and opts.smoother.window_s == 1.0
    assert dataclasses.replace(opts, pixel_noise_px=1.0) == opts.replace(pixel_noise_px=1.0)
    assert opts.replace(pixel_noise_px=1.0).velocity_noise_mps == 0.5  # the rest is kept
    assert FilterOptions(noise=NoiseOptions(velocity_mps=0.5), smoother_window_s=1.0) == opts
    assert FilterOptions(noise={"velocity_mps": 0.5}, smoother={"window_s": 1.0}) == opts
    # flat names apply on top of a group given in the same call
    assert FilterOptions(noise=NoiseOptions(velocity_mps=0.1), velocity_noise_mps=0.5).velocity_noise_mps == 0.5
    assert hash(opts) == hash(FilterOptions(velocity_noise_mps=0.5, smoother_window_s=1.0))
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.velocity_noise_mps = 1.0  # the flat names are read-only
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.noise.velocity_mps = 1.0
    with pytest.raises(TypeError, match="did you mean 'velocity_noise_mps'"):
        FilterOptions(velocity_noise=0.5)
    with pytest.raises(ConfigError, match="smoother_window_s must be > 0"):
        opts.replace(smoother_window_s=0.0)
    with pytest.raises(ConfigError, match="min_depth_m must be smaller than max_depth_m"):
        FilterOptions(min_depth_m=10.0, max_depth_m=5.0)


def test_every_field_documents_its_kind_unit_and_checks():
    for flat, (group, name) in FLAT_FIELDS.items():
        f = {f.name: f for f in dataclasses.fields(OPTION_GROUPS[group])}[name]
        meta = f.metadata
        assert meta["kind"] in KINDS and meta["doc"] and "\n" not in meta["doc"], flat
        assert check_value(flat, f.default, meta) == f.default  # the default is valid
        if meta["kind"] == "choice":
            with pytest.raises(ConfigError, match=flat):
                check_value(flat, "no-such-choice", meta)
        if meta["kind"] in ("number", "integer") and meta["range"] is not None and meta["range"][0] is not None:
            with pytest.raises(ConfigError, match=flat):
                check_value(flat, meta["range"][0] - 1, meta)
        if meta["kind"] == "bool":
            with pytest.raises(ConfigError, match="true or false"):
                check_value(flat, 1, meta)


def test_run_help_shows_the_common_flags_first_and_groups_the_rest(capsys):
    from vislam.cli import main

    with pytest.raises(SystemExit) as info:
        main(["run", "--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    common = text.index("common options:")
    for flag in ("--mode", "--out", "--config", "--velocity-noise", "--angular-noise", "--auto", "--gt FILE",
                 "--quiet"):
        assert common < text.index(f"  {flag}") < text.index("filter options: "), flag
    for title in ("noise model", "gating and rejection", "update", "IMU-error state", "smoother"):
        assert f"filter options: {title}:" in text
    assert "[pixel_noise_px = noise.pixel_px]" in " ".join(text.split())  # the option each flag sets


def test_the_docs_page_holds_the_generated_reference():
    from conftest import REPO_ROOT
    from vislam.core.options import reference_markdown

    text = (REPO_ROOT / "docs" / "options.md").read_text(encoding="utf-8")
    block = text.split("<!-- options-reference:begin -->\n", 1)[1].split("<!-- options-reference:end -->", 1)[0]
    assert block == reference_markdown(), "regenerate docs/options.md's reference with reference_markdown()"


def test_sweep_specs_take_nested_option_sets(tmp_path):
    from vislam.tools.sweep import parse_spec

    (tmp_path / "nested.yaml").write_text("noise:\n  velocity_mps: 0.5\ngating:\n  probability: off\n")
    spec = parse_spec({"datasets": ["a.npz"], "options": {
        "inline": {"noise": {"velocity_mps": 0.5}, "gating_probability": "none"}, "file": "nested.yaml",
        "flat": {"velocity_noise_mps": 0.5, "gating_probability": None}}}, source="spec.yaml", base_dir=tmp_path)
    assert spec.options["inline"] == spec.options["file"] == spec.options["flat"] \
        == {"velocity_noise_mps": 0.5, "gating_probability": None}
    with pytest.raises(ConfigError, match="did you mean 'velocity_mps'"):
        parse_spec({"datasets": ["a.npz"], "options": {"bad": {"noise": {"velocity": 0.5}}}}, source="spec.yaml",
                   base_dir=tmp_path)


def test_chi2_4_gate_is_scipys_quantile_and_inverts_the_survival_function():
    """The gate is the p-quantile of χ²₄: it agrees with scipy.special.chdtri(4, 1 − p)
    to rounding over the gate probabilities in use, and the closed-form survival function
    e^(−x/2) (1 + x/2) at it gives back 1 − p (accurate where chdtri's 1 − p is not)."""
    import math

    import numpy as np
    from scipy.special import chdtri

    from vislam.core.options import FilterOptions, _chi2_4_quantile

    for p in np.concatenate([np.linspace(0.01, 0.999999, 2001), [0.9, 0.95, 0.99, 0.999]]):
        x = _chi2_4_quantile(float(p))
        assert x == pytest.approx(float(chdtri(4, 1.0 - p)), rel=1e-13, abs=0.0)
    for p in (1e-9, 1e-4, 0.3, 0.95, 1.0 - 1e-9):
        x = _chi2_4_quantile(p)
        assert math.exp(-x / 2) * (1 + x / 2) == pytest.approx(1.0 - p, rel=1e-12, abs=0.0)
    assert _chi2_4_quantile(None) == math.inf and _chi2_4_quantile(1.0) == math.inf
    assert _chi2_4_quantile(0.0) == 0.0
    assert FilterOptions(gating_probability=0.95).gate_threshold == pytest.approx(9.487729036781154, rel=1e-15)
