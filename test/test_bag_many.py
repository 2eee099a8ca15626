"""egovib_ros.bag.many: bag arguments expanded to bags, one task per bag."""

from __future__ import annotations

import pytest
from synthetic import random_recording

from egovib_ros.bag import write_recording
from egovib_ros.bag.many import expand_bags
from egovib_ros.errors import BagError, ConfigError


def test_expand_bags(tmp_path):
    for name in ("a/one", "a/two", "b/one", "solo"):
        write_recording(tmp_path / name, random_recording(seconds=0.01))
    (tmp_path / "a" / ".hidden").mkdir()
    (tmp_path / "empty").mkdir()
    found = expand_bags([tmp_path / "a", tmp_path / "solo"])
    assert [(str(b.relative_to(tmp_path)), str(n)) for b, n in found] == [
        ("a/one", "one"),
        ("a/two", "two"),
        ("solo", "solo"),
    ]
    assert [str(n) for _, n in expand_bags([tmp_path])] == ["a/one", "a/two", "b/one", "solo"]
    with pytest.raises(ConfigError, match="one"):
        expand_bags([tmp_path / "a", tmp_path / "b"])
    with pytest.raises(BagError, match=r"empty: no rosbag2 bags \(.*\) in this directory$"):
        expand_bags([tmp_path / "empty"])
    # its metadata.yaml lost, a bag's MCAP file is still read given itself: said
    mcap = next((tmp_path / "solo").glob("*.mcap"))
    mcap.rename(tmp_path / "empty" / mcap.name)
    with pytest.raises(BagError, match=rf"give its MCAP file itself: .*empty/{mcap.name}\)$"):
        expand_bags([tmp_path / "empty"])
    assert [b for b, _ in expand_bags([tmp_path / "missing"])] == [
        tmp_path / "missing"
    ]  # its task reports it
