"""Options files (YAML/TOML) and option precedence: defaults < file < flags."""

from __future__ import annotations

import numpy as np
import pytest

from vislam.core.options import FilterOptions
from vislam.core.simulate import SimulationOptions, simulate_drive
from vislam.errors import ConfigError, VislamError
from vislam.tools.config import load_known_poses, load_options_file, resolve_options
from vislam.tools.trajectory_io import write_kitti, write_tum

YAML_TEXT = """\
# dense datasets
velocity_noise_mps: 0.5
angular_noise_radps: 5e-2      # exponent without a dot: still a number
pixel_noise_px: 1
ekf: standard
keep_all_landmarks: true
gating_probability: null
"""

TOML_TEXT = """\
# dense datasets
velocity_noise_mps = 0.5
angular_noise_radps = 5e-2
pixel_noise_px = 1
ekf = "standard"
keep_all_landmarks = true
gating_probability = "none"
"""

EXPECTED = {"velocity_noise_mps": 0.5, "angular_noise_radps": 0.05, "pixel_noise_px": 1.0, "ekf": "standard",
            "keep_all_landmarks": True, "gating_probability": None}


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("name,text", [("f.yaml", YAML_TEXT), ("f.yml", YAML_TEXT), ("f.toml", TOML_TEXT)])
def test_yaml_and_toml_files_give_the_same_options(tmp_path, name, text):
    options = resolve_options(_write(tmp_path, name, text))
    for key, value in EXPECTED.items():
        assert getattr(options, key) == value, key
    assert isinstance(options.pixel_noise_px, float)
    # everything not in the file keeps its default
    defaults = FilterOptions()
    for key in defaults.to_dict():
        if key not in EXPECTED:
            assert getattr(options, key) == getattr(defaults, key), key
    assert options.gate_threshold == np.inf


def test_load_options_file_returns_the_raw_mapping(tmp_path):
    values = load_options_file(_write(tmp_path, "f.yaml", "velocity_noise_mps: 3e-4\nekf: oc\n"))
    assert values == {"velocity_noise_mps": 3e-4, "ekf": "oc"}
    # numbers without a digit before the dot, signed or not, are numbers too
    values = load_options_file(_write(tmp_path, "g.yaml", "a: .5\nb: -.25\nc: +.5e2\nd: ._\n"))
    assert values == {"a": 0.5, "b": -0.25, "c": 50.0, "d": "._"}
    assert load_options_file(_write(tmp_path, "empty.yaml", "# nothing\n")) == {}
    assert load_options_file(_write(tmp_path, "empty.toml", "")) == {}


def test_precedence_defaults_file_flags(tmp_path):
    path = _write(tmp_path, "f.yaml", "velocity_noise_mps: 0.5\nangular_noise_radps: 0.05\n")
    defaults = FilterOptions()
    assert resolve_options(None, {}) == defaults
    from_file = resolve_options(path)
    assert from_file.velocity_noise_mps == 0.5 and from_file.angular_noise_radps == 0.05
    assert from_file.pixel_noise_px == defaults.pixel_noise_px
    # a flag beats the file; unset flags (None) do not touch it
    both = resolve_options(path, {"velocity_noise_mps": 0.7, "angular_noise_radps": None, "pixel_noise_px": 3.0})
    assert both.velocity_noise_mps == 0.7
    assert both.angular_noise_radps == 0.05
    assert both.pixel_noise_px == 3.0
    # flags without a file
    assert resolve_options(None, {"gating_probability": "none"}).gating_probability is None
    assert resolve_options(None, {"gating_probability": 0.99}).gating_probability == 0.99


@pytest.mark.parametrize(
    "name,text,words",
    [
        ("unknown.yaml", "velocity_noise: 0.5\n", ["velocity_noise"]),
        ("unknown.toml", "pixel_noise = 1.0\n", ["pixel_noise"]),
        ("type.yaml", "velocity_noise_mps: fast\n", ["velocity_noise_mps", "fast"]),
        ("type.toml", 'pixel_noise_px = "two"\n', ["pixel_noise_px", "two"]),
        ("bool.yaml", "keep_all_landmarks: 3\n", ["keep_all_landmarks"]),
        ("range.yaml", "gating_probability: 1.5\n", ["gating_probability"]),
        ("choice.toml", 'ekf = "fancy"\n', ["ekf", "fancy"]),
        ("negative.yaml", "angular_noise_radps: -0.1\n", ["angular_noise_radps"]),
        # 1σ's whose squares overflow or underflow (were a traceback or a numerical failure)
        ("huge_pixel.yaml", "pixel_noise_px: 1e300\n", ["pixel_noise_px", "1e+06"]),
        ("tiny_pixel.yaml", "pixel_noise_px: 1e-300\n", ["pixel_noise_px", "1e-06"]),
        ("huge_velocity.yaml", "velocity_noise_mps: [0.1, 1e300, 0.1]\n", ["velocity_noise_mps", "1e+06"]),
        ("huge_bias.toml", "imu_bias_sigma_mps = 1e300\n", ["imu_bias_sigma_mps", "1e+06"]),
        ("huge_prior.yaml", "initial_position_std_m: 1e200\n", ["initial_position_std_m", "1e+06"]),
        ("huge_scale.yaml", "velocity_scale: 1e300\n", ["velocity_scale", "(0, 1000]"]),
        ("huge_time.yaml", "timestamp_scale: 1e300\n", ["timestamp_scale", "[1e-12, 1e+06]"]),
        ("huge_lm_prior.toml", "smoother_landmark_prior_m = 1e300\n", ["smoother_landmark_prior_m", "1e+06"]),
        ("huge_gyro_bias.yaml", "gyro_bias_radps: [1e300, 0, 0]\n", ["gyro_bias_radps", "[-1e+06, 1e+06]"]),
        ("huge_lever_arm.yaml", "cam_T_imu: [[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n",
         ["cam_T_imu", "±1000 m"]),
        ("huge_rotation.yaml", "imu_camera_rotation_correction_deg: [1e300, 0, 0]\n",
         ["imu_camera_rotation_correction_deg", "[-360, 360]"]),
        ("syntax.yaml", "velocity_noise_mps: [0.5\n", ["invalid YAML"]),
        ("syntax.toml", "velocity_noise_mps = \n", ["invalid TOML"]),
        # scalars PyYAML resolves but its constructors cannot convert (were tracebacks)
        ("underscore.yaml", "noise: ._\n", ["noise", "mapping"]),
        ("date.yaml", "velocity_noise_mps: 2001-13-45\n", ["invalid YAML", "month"]),
        ("tagged.yaml", "pixel_noise_px: !!int abc\n", ["invalid YAML", "abc"]),
        ("timestamp.yaml", "pixel_noise_px: !!timestamp 5\n", ["invalid YAML"]),
        ("deep.yaml", "a: " + "[" * 3000 + "]" * 3000 + "\n", ["invalid YAML", "nested too deeply"]),
        ("deep.toml", "a = " + "[" * 3000 + "]" * 3000 + "\n", ["invalid TOML", "nested too deeply"]),
        ("list.yaml", "- 1\n- 2\n", ["mapping"]),
        ("nested.toml", "[filter]\nvelocity_noise_mps = 0.5\n", ["filter"]),
        ("suffix.json", "{}", ["unsupported"]),
    ],
)
def test_bad_files_raise_config_error_naming_file_and_key(tmp_path, name, text, words):
    path = _write(tmp_path, name, text)
    with pytest.raises(ConfigError) as info:
        resolve_options(path)
    message = str(info.value)
    assert str(path) in message
    assert "\n" not in message
    for word in words:
        assert word in message


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(ConfigError, match="no such options file") as info:
        resolve_options(tmp_path / "missing.yaml")
    assert str(tmp_path / "missing.yaml") in str(info.value)
    (tmp_path / "dir.toml").mkdir()
    with pytest.raises(ConfigError, match="directory"):
        load_options_file(tmp_path / "dir.toml")
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00velocity")
    with pytest.raises(ConfigError, match="UTF-8") as info:
        load_options_file(binary)
    assert str(binary) in str(info.value)


def test_bad_flag_value_names_the_flag_not_the_file(tmp_path):
    path = _write(tmp_path, "f.yaml", "velocity_noise_mps: 0.5\n")
    with pytest.raises(ConfigError) as info:
        resolve_options(path, {"pixel_noise_px": -1.0}, {"pixel_noise_px": "--pixel-noise"})
    assert "--pixel-noise" in str(info.value)
    assert str(path) not in str(info.value)


def test_known_poses_must_match_the_frames(tmp_path):
    drive = simulate_drive(SimulationOptions(n_frames=40))
    seq = drive.sequence
    tum, kitti = tmp_path / "p.tum", tmp_path / "p.kitti"
    write_tum(tum, seq.timestamps_s, drive.world_T_imu)
    write_kitti(kitti, drive.world_T_imu)
    np.testing.assert_allclose(load_known_poses(tum, seq), drive.world_T_imu, atol=1e-9)
    np.testing.assert_allclose(load_known_poses(kitti, seq), drive.world_T_imu, atol=1e-12)
    short = tmp_path / "short.kitti"
    write_kitti(short, drive.world_T_imu[:30])
    with pytest.raises(ConfigError, match="30 poses.*40 frames") as info:
        load_known_poses(short, seq)
    assert str(short) in str(info.value)
    shifted = tmp_path / "shifted.tum"
    write_tum(shifted, seq.timestamps_s + 1.0, drive.world_T_imu)
    with pytest.raises(ConfigError, match="timestamp"):
        load_known_poses(shifted, seq)
    garbage = tmp_path / "garbage.tum"
    garbage.write_text("1 2 3\n")
    with pytest.raises(VislamError) as info:
        load_known_poses(garbage, seq)
    assert str(garbage) in str(info.value)
