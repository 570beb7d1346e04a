"""The paper's Algorithm 1 on hand-made centroids."""

from __future__ import annotations

import pytest

from tracker.idtrack import IDTrack
from tracker.objects import Observation


def obs(*xy, t=0):
    return [Observation(x=float(x), y=float(y), t_us=t) for x, y in xy]


def ids(tracks):
    return [t.track_id for t in tracks]


def test_first_centroid_of_an_empty_tree_gets_id_1_and_far_ones_new_ids():
    tr = IDTrack(sigma=100.0)
    assert ids(tr.update(obs((0, 0)), 0)) == [1]
    # 150 > sigma: a new robot; 50 <= sigma: the same robot, its node overwritten
    assert ids(tr.update(obs((50, 0), (300, 0)), 1)) == [1, 2]
    assert tr.nodes == {1: (50.0, 0.0), 2: (300.0, 0.0)}


def test_distance_exactly_sigma_is_the_same_robot():
    tr = IDTrack(sigma=100.0)
    tr.update(obs((0, 0)), 0)
    assert ids(tr.update(obs((100, 0)), 1)) == [1]
    assert ids(tr.update(obs((200.001, 0)), 2)) == [2]


def test_nodes_are_never_deleted_and_a_returning_robot_keeps_its_id():
    tr = IDTrack(sigma=100.0)
    tr.update(obs((0, 0), (500, 500)), 0)
    for t in range(1, 50):          # robot 2 unseen for 49 steps
        tr.update(obs((t, 0)), t)
    assert set(tr.nodes) == {1, 2}
    assert ids(tr.update(obs((520, 480)), 50)) == [2]


def test_a_step_sees_the_nodes_updated_earlier_in_the_same_step():
    # the tree is rebuilt after each centroid: the 2nd centroid is compared with the
    # 1st one's new position (Algorithm 1 updates the tree inside the loop)
    tr = IDTrack(sigma=100.0)
    tr.update(obs((0, 0)), 0)
    out = tr.update(obs((90, 0), (180, 0)), 1)
    assert ids(out) == [1, 1]
    assert tr.nodes[1] == (180.0, 0.0)


def test_jump_beyond_sigma_is_a_new_robot_even_if_it_is_the_same_one():
    tr = IDTrack(sigma=100.0)
    tr.update(obs((0, 0)), 0)
    assert ids(tr.update(obs((101, 0)), 1)) == [2]
    assert tr.next_id == 3


def test_sigma_must_be_positive():
    with pytest.raises(ValueError, match="sigma"):
        IDTrack(sigma=0)
