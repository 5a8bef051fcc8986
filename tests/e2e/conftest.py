"""End-to-end runs (CLIs in subprocesses, notebooks, analysis scripts): all marked ``e2e``.

The quick loop skips them: ``python -m pytest -m "not e2e"``; CI runs everything.
"""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if HERE in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.e2e)
