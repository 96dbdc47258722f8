"""pilight.atomic: outputs appear whole or not at all."""

import numpy as np
import pytest
from PIL import Image

from pilight import atomic


def test_writes_land_under_the_final_name_without_leftovers(tmp_path):
    atomic.write_json(tmp_path / "m" / "metrics.json", {"b": 1, "a": 2}, sort_keys=True)
    atomic.write_text(tmp_path / "report.md", "| a |\n")
    atomic.write_png(tmp_path / "grid.png", np.full((4, 6, 3), 200, np.uint8))
    assert (tmp_path / "m" / "metrics.json").read_text() == '{\n "a": 2,\n "b": 1\n}\n'
    assert (tmp_path / "report.md").read_text() == "| a |\n"
    assert np.asarray(Image.open(tmp_path / "grid.png")).shape == (4, 6, 3)
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["grid.png", "metrics.json", "report.md"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "grid.png"
    atomic.write_png(target, np.zeros((2, 2, 3), np.uint8))
    before = target.read_bytes()
    with pytest.raises(TypeError):
        atomic.write_png(target, np.zeros((2, 2, 3), object))  # fails inside the writer, after the temporary exists
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["grid.png"]


def test_figure_format_follows_the_final_suffix(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    atomic.save_figure(fig, tmp_path / "trade.png", dpi=50)
    plt.close(fig)
    assert (tmp_path / "trade.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
