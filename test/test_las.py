"""LAS/LAZ reading: a file cut short is called truncated, whatever laspy says of it."""
from __future__ import annotations

import re

import laspy
import pytest

from conftest import data_file
from lidar_obstacles.errors import LasError
from lidar_obstacles.io.las import read_las

SAMPLE = "isprs/samp11-utm.laz"


def test_a_truncated_laz_file_is_named_as_such(tmp_path):
    full = data_file(SAMPLE).read_bytes()
    cut = tmp_path / "trunc.laz"
    cut.write_bytes(full[:len(full) // 2])  # (lazrs: "IoError: failed to fill whole buffer")
    with pytest.raises(LasError, match=rf"^cannot read LAS file {re.escape(str(cut))}: "
                                       r"truncated or corrupt \(.+\)$"):
        read_las(cut)


@pytest.mark.parametrize("records_left", [1000, 1000.5, 0])
def test_a_truncated_las_file_is_named_as_such(tmp_path, records_left):
    """Cut inside a record laspy failed with "buffer size must be a multiple of element
    size"; cut between records it read the points left without a word (none: "no points")."""
    full = tmp_path / "full.las"
    laspy.read(str(data_file(SAMPLE))).write(str(full))
    with laspy.open(str(full)) as reader:
        header = reader.header
    cut = tmp_path / "trunc.las"
    cut.write_bytes(full.read_bytes()[:header.offset_to_point_data
                                      + int(records_left * header.point_format.size)])
    with pytest.raises(LasError, match=rf"^cannot read LAS file {re.escape(str(cut))}: "
                                       r"truncated or corrupt \(\d+ bytes, but its header "
                                       r"says 38010 points"):
        read_las(cut)
    assert len(read_las(full).points) == 38010  # (the whole file is read as before)
