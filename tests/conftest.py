"""Shared fixtures: every test writes artifacts to its own temporary folder."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _isolated_outputs(tmp_path, monkeypatch):
    monkeypatch.setenv("E2E_LITE_OUTPUTS", str(tmp_path / "outputs"))
    monkeypatch.delenv("E2E_LITE_QUICK", raising=False)
