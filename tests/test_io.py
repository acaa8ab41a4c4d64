"""Atomic writes leave files and directories with the permissions of any new file."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# Written in a child process: the umask belongs to the process, and this one's stays as it is.
WRITE = """
import json, os, sys
from pathlib import Path
from quadformer.io import atomic_dir, atomic_path, atomic_write_text, write_json

os.umask(int(sys.argv[2], 8))
root = Path(sys.argv[1])
(root / "plain.txt").write_text("x")
(root / "plain_dir").mkdir()
atomic_write_text(root / "text.txt", "x")
write_json(root / "doc.json", {"a": 1})
with atomic_path(root / "by_name.bin") as tmp:
    tmp.write_bytes(b"x")
with atomic_dir(root / "dataset") as tmp:
    (tmp / "inside.json").write_text("{}")
with atomic_dir(root / "dataset", overwrite=True) as tmp:      # replacing an existing directory
    (tmp / "inside.json").write_text("{}")
print(json.dumps({p.name: p.stat().st_mode & 0o777 for p in root.iterdir()}))
"""


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o077], ids=oct)
def test_atomic_writes_honour_the_umask(umask, tmp_path):
    out = subprocess.run([sys.executable, "-c", WRITE, str(tmp_path), oct(umask)],
                         capture_output=True, text=True, check=True).stdout
    modes = json.loads(out)
    assert set(modes) == {"plain.txt", "plain_dir", "text.txt", "doc.json", "by_name.bin", "dataset"}  # no leftovers
    file_mode, dir_mode = 0o666 & ~umask, 0o777 & ~umask
    assert modes["plain.txt"] == file_mode and modes["plain_dir"] == dir_mode
    for name in ("text.txt", "doc.json", "by_name.bin"):
        assert modes[name] == file_mode, (name, oct(modes[name]))
    assert modes["dataset"] == dir_mode, oct(modes["dataset"])


def test_write_csv_reads_back_to_the_same_values_and_leaves_no_temporary_file(tmp_path):
    import numpy as np
    import pandas as pd

    from quadformer.io import write_csv

    frame = pd.DataFrame({"t": [0.1, 0.2 + 1e-13, np.nan], "n": np.array([1, 2, 3], np.int8),
                          "whole": [3.0, -2.0, 1e20], "alarm": [True, False, True],
                          "reason": ["fix lost", "capture: satellites 6, noise 139", None], "tiny": [5e-324, -0.0, np.inf]})
    path = write_csv(tmp_path / "scores.csv", frame)
    back = pd.read_csv(path)
    assert list(back.columns) == list(frame.columns)
    assert path.read_text().splitlines()[0] == "t,n,whole,alarm,reason,tiny"     # the header as pandas writes it
    for c in ("t", "n", "whole", "tiny"):              # every float to the last bit, NaN and inf included
        np.testing.assert_array_equal(back[c].to_numpy(float), frame[c].to_numpy(float))
    assert back.alarm.tolist() == [True, False, True]
    assert back.reason.iloc[1] == "capture: satellites 6, noise 139" and pd.isna(back.reason.iloc[2])
    assert [p.name for p in tmp_path.iterdir()] == ["scores.csv"]
