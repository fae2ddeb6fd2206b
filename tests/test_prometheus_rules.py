"""deploy/prometheus/alerts.yaml: valid for Prometheus (promtool check rules) and each alert fires when it
should and stays quiet otherwise (promtool test rules on deploy/prometheus/alerts_test.yaml)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RULES = ROOT / "deploy" / "prometheus"
PROMTOOL = shutil.which("promtool")
needs_promtool = pytest.mark.skipif(
    PROMTOOL is None, reason="promtool not installed (Debian: apt-get install prometheus; .ci/run installs it)"
)


def promtool(*args: str) -> subprocess.CompletedProcess[str]:
    assert PROMTOOL is not None
    return subprocess.run([PROMTOOL, *args], capture_output=True, text=True, timeout=120, cwd=RULES)


@needs_promtool
def test_alert_rules_are_valid() -> None:
    done = promtool("check", "rules", "alerts.yaml")
    assert done.returncode == 0, done.stdout + done.stderr
    rules = (RULES / "alerts.yaml").read_text("utf-8").count("- alert: ")
    assert rules >= 6 and f"SUCCESS: {rules} rules found" in done.stdout


@needs_promtool
def test_alert_rules_unit_tests_pass() -> None:
    done = promtool("test", "rules", "alerts_test.yaml")
    assert done.returncode == 0, done.stdout + done.stderr


@needs_promtool
def test_the_unit_tests_catch_a_rule_that_never_fires(tmp_path: Path) -> None:
    """The unit tests have teeth: a broken threshold fails them."""
    broken = (RULES / "alerts.yaml").read_text("utf-8").replace("gcdtrav_healthy == 0", "gcdtrav_healthy == 2")
    (tmp_path / "alerts.yaml").write_text(broken, "utf-8")
    shutil.copy(RULES / "alerts_test.yaml", tmp_path)
    done = subprocess.run(
        [str(PROMTOOL), "test", "rules", "alerts_test.yaml"], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert done.returncode != 0 and "GcdtravInstanceUnhealthy" in done.stdout + done.stderr
