"""Atomic outputs replace only a file of their own kind: a folder, or a file of another
kind, is the user's data."""
from __future__ import annotations

import pytest

from lidar_obstacles.errors import OutputError
from lidar_obstacles.io.atomic import (HTML, JSON, LAS, PNG, TIFF, YAML, atomic_write,
                                       atomic_write_text, check_replaceable)

# The first bytes of a file of each kind, as their writers make them.
SAMPLES = {
    "TIFF (II)": (TIFF, b"II*\x00\x08\x00\x00\x00"),
    "TIFF (MM)": (TIFF, b"MM\x00*\x00\x00\x00\x08"),
    "PNG": (PNG, b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR"), "LAS": (LAS, b"LASF\x00\x00\x01\x02"),
    "JSON": (JSON, b'{\n  "messages": 3\n}\n'), "JSON list": (JSON, b" [1, 2]"),
    "HTML": (HTML, b"<!DOCTYPE html><html lang='en'></html>\n"),
    "params YAML": (YAML, b"# tuned\n/**:\n  ros__parameters:\n    use_odometry: true\n"),
}


@pytest.mark.parametrize("sample", sorted(SAMPLES))
def test_an_output_replaces_only_a_file_of_its_kind(sample, tmp_path):
    kind, same = SAMPLES[sample]
    path = tmp_path / "out"
    path.write_bytes(same)
    atomic_write(path, lambda tmp: tmp.write_bytes(same + b"new"), kind=kind)
    assert path.read_bytes() == same + b"new"
    others = [b"hi\n", b"\x00\x01binary"] + [b for k, b in SAMPLES.values() if k != kind]
    for other in others:
        path.write_bytes(other)
        with pytest.raises(OutputError) as err:
            atomic_write(path, lambda tmp: tmp.write_bytes(same), kind=kind)
        assert str(err.value) == f"{path} exists and is not {kind.name}: not overwriting it"
        assert path.read_bytes() == other
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary file left


def test_an_empty_file_is_replaced_and_a_folder_never(tmp_path):
    empty = tmp_path / "made_by_mktemp.json"
    empty.touch()
    atomic_write_text(empty, "{}\n", kind=JSON)
    assert empty.read_text() == "{}\n"
    folder = tmp_path / "dem.tif"
    folder.mkdir()
    with pytest.raises(OutputError, match="exists and is not a TIFF"):
        check_replaceable(folder, TIFF)
    check_replaceable(tmp_path / "new.tif", TIFF)  # nothing there: fine
