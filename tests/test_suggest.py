"""Misspelt names get "did you mean": option keys of an options file, flags, commands,
choices, sweep-spec keys — one line and exit 2, as every user mistake."""

from __future__ import annotations

import pytest

from vislam.cli import main
from vislam.core.options import FilterOptions
from vislam.core.suggest import close_matches, did_you_mean, unknown_names_message
from vislam.errors import ConfigError
from vislam.tools.config import resolve_options
from vislam.tools.sweep import parse_spec


def test_close_matches_finds_the_misspelt_name_first():
    known = ["velocity_noise_mps", "angular_noise_radps", "pixel_noise_px"]
    assert close_matches("velocty_noise_mps", known)[0] == "velocity_noise_mps"
    assert close_matches("PIXEL_NOISE_PX", known)[0] == "pixel_noise_px"
    assert did_you_mean("warp", known) == ""


def test_unknown_names_message_lists_the_known_names_only_without_a_match():
    assert unknown_names_message("key", ["modse"], ["modes", "seeds"]) == "unknown key 'modse'; did you mean 'modes'?"
    assert unknown_names_message("key", ["zzz"], ["modes", "seeds"]) == "unknown key 'zzz'; known: modes, seeds"


def test_options_file_key_gets_did_you_mean(tmp_path):
    path = tmp_path / "opts.yaml"
    path.write_text("velocty_noise_mps: 0.5\n")
    with pytest.raises(ConfigError) as info:
        resolve_options(path)
    message = str(info.value)
    assert str(path) in message and "'velocty_noise_mps'" in message
    assert "did you mean 'velocity_noise_mps'" in message
    assert "known:" not in message  # not the list of every option
    with pytest.raises(ConfigError, match="did you mean 'pixel_noise_px'"):
        FilterOptions.from_dict({"pixel_noise": 2.0})


def test_sweep_spec_key_gets_did_you_mean(tmp_path):
    with pytest.raises(ConfigError, match="unknown key 'modse'; did you mean 'modes'"):
        parse_spec({"datasets": ["a.npz"], "modse": ["slam"]}, source="spec.yaml", base_dir=tmp_path)


@pytest.mark.parametrize("argv, expected", [
    (["run", "d.npz", "--out", "o", "--velocty-noise", "0.5"], "--velocty-noise: did you mean '--velocity-noise'"),
    (["run", "d.npz", "--out", "o", "--pixel-noize=2"], "--pixel-noize: did you mean '--pixel-noise'"),
    (["rnu", "d.npz"], "invalid choice: 'rnu'"),
    (["run", "d.npz", "--out", "o", "--mode", "slm"], "did you mean 'slam'?"),
])
def test_misspelt_flag_command_or_choice(capsys, argv, expected, tmp_path):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert expected in err and "Traceback" not in err
    assert "did you mean" in err.splitlines()[-1]


def test_misspelt_option_file_key_on_the_command_line(capsys, tmp_path):
    (tmp_path / "o.yaml").write_text("gating_probabilty: 0.9\n")
    code = main(["run", str(tmp_path / "missing.npz"), "--config", str(tmp_path / "o.yaml"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "did you mean 'gating_probability'" in err[0]
    assert not (tmp_path / "out").exists()
