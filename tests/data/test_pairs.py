"""Relighting pairs: same scene and view, identity pairs present, deterministic from the seed."""

from __future__ import annotations

import pytest

from pilight.data.pairs import Pair, make_pairs, read_pairs, view_pairs, write_pairs
from pilight.data.schema import DataError


def test_all_pairs_by_default_with_identity():
    pairs = view_pairs("train_0001", 2, 4, seed=0, pairs_per_view=None)
    assert len(pairs) == 16 and len(set(pairs)) == 16
    assert all(p.scene == "train_0001" and p.view == 2 for p in pairs)
    assert {(p.a, p.b) for p in pairs if p.a == p.b} == {(i, i) for i in range(4)}


def test_subsampled_pairs_are_deterministic_and_local():
    kw = dict(seed=3, pairs_per_view=2)
    one = view_pairs("train_0001", 0, 5, **kw)
    assert one == view_pairs("train_0001", 0, 5, **kw)
    assert len([p for p in one if p.a != p.b]) == 2 and len(one) == 2 + 5
    # A view's draw does not depend on which other scenes exist.
    many = make_pairs([("train_0000", 0, 5), ("train_0001", 0, 5)], **kw)
    assert [p for p in many if p.scene == "train_0001"] == one
    seeds = {tuple(view_pairs("train_0001", 0, 5, seed=s, pairs_per_view=2)) for s in range(10)}
    assert len(seeds) > 1


def test_identity_can_be_left_out():
    pairs = view_pairs("val_0000", 0, 3, seed=0, pairs_per_view=None, identity=False)
    assert len(pairs) == 6 and all(p.a != p.b for p in pairs)


def test_file_round_trip_and_bad_file(tmp_path):
    pairs = make_pairs([("test_0000", 0, 2), ("test_0000", 1, 2)], seed=0, pairs_per_view=None)
    write_pairs(tmp_path / "p.tsv", pairs)
    assert read_pairs(tmp_path / "p.tsv") == pairs and isinstance(pairs[0], Pair)
    (tmp_path / "bad.tsv").write_text("scene\tview\tlight_a\tlight_b\ntest_0000\t0\tx\t1\n")
    with pytest.raises(DataError, match="bad.tsv:2"):
        read_pairs(tmp_path / "bad.tsv")
    with pytest.raises(DataError, match="not found"):
        read_pairs(tmp_path / "none.tsv")
