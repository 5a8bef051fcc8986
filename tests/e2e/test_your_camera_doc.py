"""``docs/your-camera.md`` can be followed verbatim: its ``bash`` code blocks run as they stand.

The page's ```` ```bash ```` blocks are extracted in order and run, unchanged, by ``bash -e`` in
a fresh folder laid out like a checkout (``repo/`` as the working directory, ``shared/data``
beside it linking to the real data), so that the page's ``../shared/data/dlmd_mirflickr``
resolves. Every block must exit 0; the outputs the page talks about must be there.

Every block runs, in CI too (the page is tested as it stands). A block whose fence is
preceded by the line ``<!-- doc-test: long -->`` (invisible in the rendered page) may be left
out of a quick local loop with ``EKDUN_DOC_TEST_LONG=0``; since a skipped block's outputs do
not exist, every block after a long one must be long too (checked here), so the quick run is a
prefix of the page. The long blocks are training, reconstruction with the network and its
evaluation (steps 4-6; about a minute on a CPU); the rest is the fits, ``eval-model`` and
``ekdun reconstruct`` with the kernel files (steps 1-3), whose time is that of the two
fit-pairs runs at 4× binning.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
PAGE = REPO / "docs" / "your-camera.md"
LONG_MARKER = "<!-- doc-test: long -->"
LONG_ENV = "EKDUN_DOC_TEST_LONG"
_BLOCK = re.compile(r"(?P<marker>^<!-- doc-test: long -->\n)?^```bash\n(?P<code>.*?)^```$",
                    re.MULTILINE | re.DOTALL)


def bash_blocks(text: str) -> list[tuple[str, bool]]:
    """``(code, long)`` of every ```` ```bash ```` block of ``text``, in order."""
    return [(m.group("code"), m.group("marker") is not None) for m in _BLOCK.finditer(text)]


def test_the_blocks_are_found_and_long_ones_come_last():
    text = PAGE.read_text(encoding="utf-8")
    blocks = bash_blocks(text)
    assert len(blocks) == text.count("```bash") >= 6
    assert text.count(LONG_MARKER) == sum(long for _, long in blocks)   # every marker is seen
    flags = [long for _, long in blocks]
    assert flags == sorted(flags), "a block after a long one must be long too"
    commands = "\n".join(code for code, _ in blocks)
    for step in ("psfkit fit-pairs", "psfkit eval-model", "ekdun reconstruct si.npz", "ekdun train",
                 "ekdun reconstruct", "ekdun eval"):
        assert step in commands


def test_every_code_block_runs_as_it_stands(real_data, tmp_path):
    data = real_data("dlmd_mirflickr").parent
    (tmp_path / "shared").mkdir()
    (tmp_path / "shared" / "data").symlink_to(data, target_is_directory=True)
    work = tmp_path / "repo"
    work.mkdir()
    env = dict(os.environ)
    # the commands of the environment running the tests (its psfkit and ekdun)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    run_long = os.environ.get(LONG_ENV, "1") != "0"
    ran = []
    for i, (code, long) in enumerate(bash_blocks(PAGE.read_text(encoding="utf-8"))):
        if long and not run_long:
            continue
        done = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", code], cwd=work, env=env,
                              capture_output=True, text=True)
        assert done.returncode == 0, (f"block {i + 1} of {PAGE.name} failed:\n{code}\n"
                                      f"stderr:\n{done.stderr[-3000:]}")
        ran.append(code)
    assert ran
    # what the page says each step leaves behind
    for name in ("si.npz", "ek.npz", "eval.json", "eval_residual.png", "eval_residual.npz",
                 "recon_admm/si/im65.npy", "recon_admm/ek/im65.npy"):
        assert (work / name).is_file(), name
    doc = json.loads((work / "eval.json").read_text())
    for result in doc["models"]:
        assert result["held_out"]["pairs"] == ["im65"]
        assert result["fitted"]["pairs_count"] == 6
        assert set(result["held_out"]["by_zone"]) == {"centre", "middle", "edge"}
    if run_long:
        assert (work / "recon" / "im65.npy").is_file()
        results = json.loads((work / "tables" / "results.json").read_text())["results"]
        assert results[0]["pairs"] == ["im65"] and "by_zone" in results[0]
