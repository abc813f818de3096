"""``mso validate`` checks what deploy would: the app's policy and its params; an app whose
code cannot be imported says how code reaches every node."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

APP = (
    "name: bot\n{policy}vertices:\n  camera: {{code: {code}}}\n  B: {{}}\nedges:\n  - [camera, B]\n"
)
OK_CODE = "mso.examples.convoy.sensors:Odometer"


@pytest.mark.parametrize(
    ("policy", "code", "expected"),
    [
        ("policy: fast\n", OK_CODE, "policy: unknown policy 'fast' (expected one of balance"),
        (
            "policy: {name: lifetime, params: {speed: 3}}\n",
            OK_CODE,
            "policy: cannot create policy 'lifetime' with params {'speed': 3}",
        ),
        (
            "",
            "visionbot.camera:Camera",
            "no module named 'visionbot' (app code must be importable on every node: install "
            "its package there, e.g. pip install -e ., or put it on PYTHONPATH; nodes run only "
            "allowed code: --allow-code visionbot",
        ),
        (
            "policy: visionbot.policy:Mine\n",
            OK_CODE,
            "policy: import path 'visionbot.policy:Mine' does not resolve: no module named "
            "'visionbot' (app code must be importable on every node",
        ),
    ],
)
def test_validate_reports_what_deploy_would(
    tmp_path: Path, policy: str, code: str, expected: str
) -> None:
    app = tmp_path / "bot.yaml"
    app.write_text(APP.format(policy=policy, code=code))
    r = subprocess.run(
        [sys.executable, "-m", "mso", "validate", str(app)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 2 and r.stdout == "", r
    assert r.stderr.count("\n") == 1 and expected in r.stderr, r.stderr
    if policy:  # file:line: field, as every other problem
        assert f"{app}:2: policy: " in r.stderr


def test_a_good_policy_validates(tmp_path: Path) -> None:
    app = tmp_path / "bot.yaml"
    app.write_text(APP.format(policy="policy: {name: lifetime}\n", code=OK_CODE))
    r = subprocess.run(
        [sys.executable, "-m", "mso", "validate", str(app)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 0 and "ok (2 vertices, 1 edges)" in r.stdout, r
