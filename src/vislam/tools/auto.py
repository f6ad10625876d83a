"""``--auto``: check a recording first and run with its suggestions — one code path for
``vislam run --auto``, ``vislam compare --auto`` and ``vislam report`` (every dataset).

* :func:`auto_check` runs :func:`vislam.core.check.check_sequence` on the sequence the
  filter will see and returns the record stored under ``"auto"`` in summary.json /
  comparison.json: ``{"suggested": {FilterOptions field: value}, "findings": [{code,
  severity, message}], "check_seconds": s}``;
* :func:`auto_options` turns a record into FilterOptions: defaults < suggestions <
  options file < overrides (:func:`vislam.tools.config.resolve_options`);
* :func:`findings_to_print` are the findings a command prints (those not OK);
* :func:`describe_suggestions` says in a few words what the suggestions change (for
  tables and the report).
"""

from __future__ import annotations

from typing import Any, Mapping

from vislam.core.options import FilterOptions
from vislam.core.sequence import Sequence

__all__ = ["auto_check", "auto_options", "findings_to_print", "describe_suggestions"]


def auto_check(sequence: Sequence) -> dict[str, Any]:
    """Check ``sequence`` (:func:`vislam.core.check.check_sequence`) and return the
    ``"auto"`` record: the suggested options, the findings and the check's time."""
    from vislam.core.check import check_sequence

    check = check_sequence(sequence)
    return {"suggested": dict(check.suggested), "findings": [f.to_dict() for f in check.findings],
            "check_seconds": check.elapsed_s}


def auto_options(record: Mapping[str, Any] | None, config_path=None, overrides: Mapping[str, Any] | None = None,
                 flag_names: Mapping[str, str] | None = None) -> FilterOptions:
    """FilterOptions of defaults < ``record``'s suggestions < ``config_path`` < ``overrides``."""
    from vislam.tools.config import resolve_options

    suggested = (record or {}).get("suggested") or None
    return resolve_options(config_path, overrides, flag_names, base=suggested)


def findings_to_print(record: Mapping[str, Any]) -> list[str]:
    """One line per finding that is not OK, as the commands print them on stderr."""
    return [f"vislam check: {f['severity']} {f['code']}: {f['message']}" for f in record.get("findings", ())
            if f["severity"] != "OK"]


def _g(x) -> str:
    if isinstance(x, (list, tuple)):
        return "(" + ", ".join(f"{v:.3g}" for v in x) + ")"
    return f"{x:.3g}" if isinstance(x, float) else str(x)


_UNITS = {"velocity_noise_mps": "m/s", "angular_noise_radps": "rad/s", "pixel_noise_px": "px",
          "gyro_bias_radps": "rad/s", "velocity_bias_mps": "m/s", "imu_camera_rotation_correction_deg": "deg",
          "time_offset_s": "s"}


def describe_suggestions(record: Mapping[str, Any] | None) -> str:
    """``"velocity_noise_mps (0.513, 0.52, 0.497) m/s, gyro_bias_radps (0, 0.005, 0) rad/s"``,
    or ``"none (the defaults fit)"`` when the check suggested nothing."""
    suggested = (record or {}).get("suggested") or {}
    if not suggested:
        return "none (the defaults fit)"
    return ", ".join(_describe(k, v) for k, v in suggested.items())


def _describe(key: str, value) -> str:
    if key == "cam_T_imu":  # a 4x4: what changes is the lever arm, said by its translation
        return f"cam_T_imu with translation {_g([float(row[3]) for row in value[:3]])} m"
    return f"{key} {_g(value)}" + (f" {_UNITS[key]}" if key in _UNITS else "")
