"""The scaling benchmarks skip shard counts a scene cannot be placed on (the default K list
follows the machine's cores: up to 14 on 16 cores), with a line that says so, instead of
failing after the smaller K have run. The rule is the partitioner's own."""

import numpy as np
import pytest

from bench.common import placeable_ks
from nprt.scene.errors import SceneError
from nprt.scene.io import scene_from_meshes
from nprt.scene.model import Material
from nprt.scene.partition import partition
from tests.proxies.helpers import box


def _three_boxes():
    moves = [np.eye(4) for _ in range(3)]
    for i, m in enumerate(moves):
        m[0, 3] = 2.0 * i
    return scene_from_meshes([box()], [(0, m) for m in moves], (Material(),), "three")


def test_shard_counts_above_the_instance_count_are_skipped_and_named(capsys):
    scene = _three_boxes()
    assert placeable_ks([1, 2, 3, 4, 8], scene, "three") == [1, 2, 3]
    assert "three: 3 instances, so K = 4, 8 skipped" in capsys.readouterr().out
    assert placeable_ks([1, 2], scene, "three") == [1, 2]
    assert capsys.readouterr().out == ""


def test_the_rule_is_the_partitioners():
    scene = _three_boxes()
    assert partition(scene, 3).k == 3
    with pytest.raises(SceneError, match="only 3 instances"):
        partition(scene, 4)
