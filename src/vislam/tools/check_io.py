"""Output of ``vislam check``: ``check.json`` and ``suggested.yaml``, written together.

* ``check.json`` — every estimate of :class:`vislam.core.check.CheckResult` with its
  uncertainty (``*_se``: standard errors), the ``findings`` list of
  ``{code, severity, message}`` and ``suggested_options``;
* ``suggested.yaml`` — a flat options file for ``vislam run --config`` that sets what
  check suggests (noise per axis, gyro bias, IMU-camera rotation correction, velocity
  association, time offset). The data file is never edited.

Both are staged and committed together (:class:`vislam.tools.outputs.OutputStage`): a
failure leaves the directory as it was.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from vislam.core.check import CheckResult
from vislam.tools.jsonio import dumps, json_safe
from vislam.tools.outputs import OutputStage

__all__ = ["CHECK_JSON", "SUGGESTED_YAML", "suggested_yaml_text", "write_check_outputs", "format_verdict"]

CHECK_JSON = "check.json"
SUGGESTED_YAML = "suggested.yaml"


def suggested_yaml_text(result: CheckResult) -> str:
    """The text of suggested.yaml (comments name the recording and each finding acted on)."""
    lines = [f"# vislam check suggestions for {result.source or result.name}",
             "# use with: vislam run DATA --config suggested.yaml"]
    for f in result.findings:
        if f.severity != "OK":
            lines.append(f"# {f.severity} {f.code}")
    body = yaml.safe_dump(json_safe(result.suggested), sort_keys=False, default_flow_style=None) \
        if result.suggested else "{}\n"
    return "\n".join(lines) + "\n" + body


def write_check_outputs(result: CheckResult, out_dir) -> list[Path]:
    """Write check.json and suggested.yaml into ``out_dir`` (all or nothing)."""
    with OutputStage(out_dir) as stage:
        stage.path(CHECK_JSON).write_text(dumps(result.to_dict()) + "\n", encoding="utf-8")
        stage.path(SUGGESTED_YAML).write_text(suggested_yaml_text(result), encoding="utf-8")
        return stage.commit(order=(CHECK_JSON, SUGGESTED_YAML), remove_stale=())


def format_verdict(result: CheckResult) -> str:
    """One line per finding: ``SEVERITY code: message``."""
    width = max((len(f.code) for f in result.findings), default=0)
    lines = [f"{f.severity:<5} {f.code:<{width}}  {f.message}" for f in result.findings]
    lines.append(f"checked {result.source or result.name} in {result.elapsed_s:.1f} s; worst: {result.worst_severity}")
    return "\n".join(lines)
