"""`bh8 serve` against hostile and clumsy input (issue 19): floods, bad stores, bad objects and
options. The server must answer with a clear error or keep serving, with bounded memory and CPU,
and must always save its never-reset counters on the way out (manual §5.3.2, §5.4.2).
"""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bh8_gym.cli import main

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pty tests need Linux /dev/pts")


@pytest.mark.parametrize("state", ["", "   "])
def test_an_empty_state_directory_is_refused_not_the_working_directory(state, tmp_path, monkeypatch, capsys):
    """`--state ""` was Path("") = ".": the store went into ./nvstore.json. Refused as
    bh8sim://?state= refuses an empty value (usage error, exit 2), before any store is made."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stopped:
        main(["serve", "--state", state])
    assert stopped.value.code == 2
    assert "--state: needs a directory, got an empty value" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
