"""Inputs of a run besides the dataset: filter options and known poses.

Option resolution (lowest to highest precedence):

1. the documented defaults of :class:`~vislam.core.options.FilterOptions`;
1b. with ``vislam run --auto``, the suggestions of ``vislam check`` (``base``);
2. an options file (``--config FILE``): YAML (``.yaml``/``.yml``) or TOML (``.toml``),
   a mapping of FilterOptions' flat names to values, of its groups to their fields, or
   both (an option given both ways is an error), e.g.::

       # filter.yaml                       # filter.toml
       velocity_noise_mps: 0.5             velocity_noise_mps = 0.5
       angular_noise_radps: 0.05           angular_noise_radps = 0.05
       gating_probability: null            gating_probability = "none"

       # the same, nested                  # the same, nested
       noise:                              [noise]
         velocity_mps: 0.5                 velocity_mps = 0.5
         angular_radps: 0.05               angular_radps = 0.05
       gating:                             [gating]
         probability: null                 probability = "none"

   The optional tests (``gating_probability``, ``drift_test_probability``,
   ``smoother_drift_ratio``) accept ``null`` (YAML), ``false`` or the string
   ``"none"`` (TOML has no null) to switch the test off. YAML numbers in exponent
   form without a dot (``3e-4``) are read as numbers, not strings (PyYAML follows
   YAML 1.1 there; we do not);
3. command-line flags (``overrides``).

Every problem — a missing, unreadable or syntactically broken file, an unknown key, a
value of the wrong type or out of range — is a :class:`~vislam.errors.ConfigError` whose
one-line message names the file (or the flag) and the key.

:func:`load_known_poses` reads the poses of ``--poses FILE`` (mapping with given poses).
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from vislam.core.options import FilterOptions, flatten_options
from vislam.errors import ConfigError

__all__ = ["CONFIG_SUFFIXES", "OPTIONAL_FIELDS", "read_config_document", "load_options_file", "resolve_options", "load_known_poses",
           "POSE_TIME_TOLERANCE_S"]

#: File suffix -> format.
CONFIG_SUFFIXES = {".yaml": "yaml", ".yml": "yaml", ".toml": "toml"}
#: FilterOptions fields that may be switched off (None).
OPTIONAL_FIELDS = ("gating_probability", "drift_test_probability", "smoother_drift_ratio")
#: Largest difference (s) between a TUM pose file's timestamps and the dataset's.
POSE_TIME_TOLERANCE_S = 0.02

_OFF_WORDS = ("none", "null", "off")


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads ``1e-3`` / ``5E+2`` (no dot) and ``-.5`` as floats and refuses a
    key given twice in one mapping (plain YAML silently keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                duplicate = key in seen
                seen.add(key)
            except TypeError:  # unhashable key: let the base class report it
                duplicate = False
            if duplicate:
                raise yaml.constructor.ConstructorError(None, None, f"option {key!r} is given twice",
                                                        key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |[-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


#: What PyYAML's SafeLoader constructors raise, besides YAMLError, for a scalar they
#: cannot convert: ``2001-13-45`` (a date), ``!!int abc``, ``!!float x``, ``!!timestamp 5``.
YAML_VALUE_ERRORS = (ValueError, TypeError, AttributeError, OverflowError)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def read_config_document(path, what: str = "options file") -> Any:
    """The parsed document of a YAML or TOML file (by suffix), any type; every problem
    (suffix, missing file, directory, encoding, syntax) a one-line ConfigError naming
    the file and ``what`` it should be. An empty YAML file is None."""
    path = Path(path)
    fmt = CONFIG_SUFFIXES.get(path.suffix.lower())
    if fmt is None:
        raise ConfigError(f"{path}: unsupported {what} type {path.suffix or '(no suffix)'!r}; "
                          f"expected {', '.join(CONFIG_SUFFIXES)}")
    if not path.exists():
        raise ConfigError(f"{path}: no such {what}")
    if path.is_dir():
        raise ConfigError(f"{path}: is a directory ({what} expected)")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a UTF-8 text file ({fmt.upper()} {what} expected)") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    if fmt == "toml":
        try:
            return tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: invalid TOML: {_one_line(exc)}") from None
        except RecursionError:
            raise ConfigError(f"{path}: invalid TOML: nested too deeply ({what} expected)") from None
    try:
        return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or exc
        raise ConfigError(f"{path}: invalid YAML{where}: {_one_line(problem)}") from None
    except RecursionError:
        raise ConfigError(f"{path}: invalid YAML: nested too deeply ({what} expected)") from None
    except YAML_VALUE_ERRORS as exc:  # PyYAML's constructors: a tagged or date-like scalar they cannot convert
        raise ConfigError(f"{path}: invalid YAML: a value cannot be read ({_one_line(exc)})") from None


def load_options_file(path) -> dict[str, Any]:
    """The mapping of an options file (YAML or TOML, by suffix), flat: groups of options
    (``noise: {velocity_mps: 0.5}``, a ``[noise]`` table) become their flat names
    (:func:`~vislam.core.options.flatten_options`); not yet validated against
    FilterOptions (see :func:`resolve_options`). An empty YAML file is ``{}``."""
    path = Path(path)
    values = read_config_document(path, "options file")
    if values is None:
        values = {}
    if not isinstance(values, Mapping):
        raise ConfigError(f"{path}: expected a mapping of option names to values, got {type(values).__name__}")
    bad_keys = [k for k in values if not isinstance(k, str)]
    if bad_keys:
        raise ConfigError(f"{path}: option names must be strings, got {bad_keys[0]!r}")
    return flatten_options(values, source=str(path))


def _normalize(values: Mapping[str, Any]) -> dict[str, Any]:
    """Map the off-words of the optional fields to None."""
    out = dict(values)
    for key in OPTIONAL_FIELDS:
        value = out.get(key)
        if value is False or (isinstance(value, str) and value.strip().lower() in _OFF_WORDS):
            out[key] = None
    return out


def resolve_options(config_path=None, overrides: Mapping[str, Any] | None = None,
                    flag_names: Mapping[str, str] | None = None,
                    base: Mapping[str, Any] | None = None) -> FilterOptions:
    """FilterOptions from defaults < ``base`` < options file ``config_path`` < ``overrides``.

    ``base`` (e.g. the suggestions of ``vislam check``, for ``--auto``) is a mapping of
    field names to values under the file and the flags.

    ``overrides`` maps field names to values; entries whose value is None are ignored
    (an unset flag). To switch an optional test off from the command line pass the string
    ``"none"``. ``flag_names`` (field -> flag, e.g. ``{"velocity_noise_mps":
    "--velocity-noise"}``) names the flags in error messages about overridden values.
    """
    values: dict[str, Any] = {}
    if base:
        values = _normalize(base)
        FilterOptions.from_dict(values, source="check suggestions")
    if config_path is not None:
        source = str(config_path)
        file_values = _normalize(load_options_file(config_path))
        FilterOptions.from_dict(file_values, source=source)  # errors name the file
        values = {**values, **file_values}
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    if not given:
        return FilterOptions.from_dict(values, source=str(config_path) if config_path is not None else "options")
    given = _normalize(given)
    try:
        return FilterOptions.from_dict({**values, **given}, source="command line")
    except ConfigError as exc:
        message = str(exc)
        for field, flag in (flag_names or {}).items():
            if field in given:
                message = re.sub(rf"\b{re.escape(field)}\b", flag, message)
        raise ConfigError(message) from None


def load_known_poses(path, sequence) -> np.ndarray:
    """(T, 4, 4) world_T_imu poses from a TUM or KITTI file, one per frame of ``sequence``.

    The format is detected from the number of values per line. A TUM file's timestamps
    must match the dataset's (within :data:`POSE_TIME_TOLERANCE_S`). Raises
    GroundTruthError for an unreadable or malformed file, ConfigError when the poses do
    not match the dataset's frames.
    """
    from vislam.tools.trajectory_io import read_trajectory

    traj = read_trajectory(path)
    T = sequence.n_frames
    if len(traj) != T:
        raise ConfigError(f"{path}: {len(traj)} poses, but the dataset {sequence.source or sequence.name} has {T} "
                          f"frames; --poses needs one world_T_imu pose per frame")
    if traj.timestamps_s is not None:
        dt = np.abs(traj.timestamps_s - sequence.timestamps_s)
        i = int(np.argmax(dt))
        if dt[i] > POSE_TIME_TOLERANCE_S:
            raise ConfigError(f"{path}: pose {i} has timestamp {float(traj.timestamps_s[i])!r} "
                              f"but frame {i} of the dataset "
                              f"is at {float(sequence.timestamps_s[i])!r} (difference {dt[i]:.3g} s > "
                              f"{POSE_TIME_TOLERANCE_S:g} s)")
    return traj.world_T_body
