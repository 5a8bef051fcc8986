"""``ekdun train`` from the command line: the pairs folder is listed once (issue 44: it was read
twice, once to probe its size and channel order, once for the dataset)."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.e2e


def test_train_lists_the_pairs_folder_once(tiny_data, tmp_path, monkeypatch):
    import ekdun.data.pairs
    import psfkit.io.pairs
    from ekdun.cli import main

    calls = []
    original = psfkit.io.pairs.read_pairs

    def counted(*args, **kwargs):
        calls.append(args[0])
        return original(*args, **kwargs)

    monkeypatch.setattr(psfkit.io.pairs, "read_pairs", counted)
    monkeypatch.setattr(ekdun.data.pairs, "read_pairs", counted)
    pairs, kernels = tiny_data
    assert main(["train", str(pairs), str(tmp_path / "run"), "--kernels", str(kernels),
                 "--epochs", "1", "--batch-size", "4", "--iterations", "2", "--threads", "1",
                 "--device", "cpu", "--quiet"]) == 0
    assert len(calls) == 1, calls
    assert (tmp_path / "run" / "checkpoint.pt").is_file()
