"""Tests of the research studies (``research/``, not installed): all marked ``research``.

``python -m pytest -m research`` runs them alone; CI runs them with everything else. The ones
that run a study end to end (subprocesses, trainings) are also ``e2e``, skipped by the quick
loop ``-m "not e2e"``; the maths tests (identifiability) are not.
"""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if HERE in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.research)
