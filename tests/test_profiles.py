"""profiles/paper.yaml is an overlay: composed with params.yaml by `pilight profile`, every section loads
through pilight.params (the weight-path checks switched off by the explicit flag), and stage 2 is the
paper's free relit branch."""

from pathlib import Path

import pytest
import yaml

from pilight.cli import main as cli
from pilight.params import SECTIONS, ParamsError, load_section
from pilight.profiles import compose

ROOT = Path(__file__).resolve().parents[1]
PAPER, DEFAULT = ROOT / "profiles" / "paper.yaml", ROOT / "params.yaml"


@pytest.fixture()
def paper_params(tmp_path: Path) -> Path:
    out = tmp_path / "params.yaml"
    assert cli(["profile", str(PAPER), "--base", str(DEFAULT), "-o", str(out), "--no-check-paths"]) == 0
    return out


def test_paper_profile_composes_and_every_section_loads(paper_params: Path):
    raw = yaml.safe_load(paper_params.read_text())
    assert set(raw) == set(SECTIONS)
    for name in SECTIONS:
        load_section(name, paper_params, check_paths=False)
    # the overlay's values win; the keys it does not name keep the default's
    assert load_section("render", paper_params).resolution == 768
    default = yaml.safe_load(DEFAULT.read_text())
    assert raw["render"]["light"] == default["render"]["light"]
    assert raw["intrinsics"]["train"]["weight_decay"] == default["intrinsics"]["train"]["weight_decay"]


def test_the_overlay_holds_only_keys_that_differ():
    default = yaml.safe_load(DEFAULT.read_text())

    def same(base, over, where=""):
        for k, v in over.items():
            if isinstance(v, dict) and v.get("kind", base[k].get("kind")) != base[k].get("kind"):
                continue  # another choice replaces the base's mapping whole: every key of it is needed
            if isinstance(v, dict):
                yield from same(base[k], v, f"{where}{k}.")
            elif v == base[k]:
                yield f"{where}{k}"

    assert not list(same(default, yaml.safe_load(PAPER.read_text())))


def test_weight_paths_are_checked_unless_switched_off(paper_params: Path, tmp_path: Path, capsys):
    with pytest.raises(ParamsError, match="codec.path '/models/stable-diffusion-2/vae' does not exist"):
        load_section("intrinsics", paper_params)
    out = tmp_path / "checked.yaml"
    assert cli(["profile", str(PAPER), "--base", str(DEFAULT), "-o", str(out)]) == 2
    assert "--no-check-paths" in capsys.readouterr().err and not out.exists()


def test_paper_profile_uses_the_free_relit_branch_and_the_papers_renders(paper_params: Path):
    raw = yaml.safe_load(paper_params.read_text())
    # another kind of form replaces the default's mapping (its physics-first options do not leak in)
    assert raw["relight"]["form"] == {"kind": "free", "target": "image", "resolution": "full"}
    assert raw["relight"]["lambda_image"] == 0 and raw["relight"]["d_calc_condition"] == []
    assert raw["render"]["camera_backdrop"] is None


def test_a_typo_in_an_overlay_is_named(tmp_path: Path, capsys):
    with pytest.raises(ParamsError, match=r"render\.cycels: not a key"):
        compose({"render": {"cycles": {"samples": 1}}}, {"render": {"cycels": {"samples": 2}}})
    bad = tmp_path / "bad.yaml"
    bad.write_text("relight:\n  lambda_ds: 1.0\n  lambda_ds: 2.0\n")
    out = tmp_path / "out.yaml"
    assert cli(["profile", str(bad), "--base", str(DEFAULT), "-o", str(out)]) == 2
    assert str(bad) in capsys.readouterr().err and not out.exists()
    bad.write_text("relight:\n  lambda_ds: .nan\n")
    assert cli(["profile", str(bad), "--base", str(DEFAULT), "-o", str(out), "--no-check-paths"]) == 2
    assert "relight.lambda_ds" in capsys.readouterr().err and not out.exists()
