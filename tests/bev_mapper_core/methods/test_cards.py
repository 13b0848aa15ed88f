"""The shipped weights' model cards (bev_mapper_core/methods/cards.py): every file a method ships
has a full card in its metadata, docs/MODELS.md is exactly what the files say, and storing a card
rewrites the header only (the tensors stay byte for byte)."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file

from bev_mapper_core.methods import METHODS, WEIGHTS_DIR
from bev_mapper_core.methods.cards import MODELS_MD, main, read_card, read_header, render_models_md, set_card, shipped_files
from bev_mapper_core.methods.segmenter.model import Segmenter, SegmenterConfig
from bev_mapper_core.methods.segmenter.weights import load_segmenter, save_segmenter
from bev_mapper_core.nn.card import CardError


def test_docs_models_md_is_what_the_shipped_files_say():
    assert MODELS_MD.read_text() == render_models_md(), (
        "docs/MODELS.md is stale: run python -m bev_mapper_core.methods.cards write")


def test_every_shipped_weights_file_has_a_full_card():
    names = {name for spec in METHODS.values() for name in spec.weights}
    assert names == set(shipped_files()) and names
    for name in sorted(names):
        path = WEIGHTS_DIR / name
        card = read_card(path)
        assert card is not None, f"{name} has no model card"
        _, meta, _ = read_header(path)
        classes = meta.get("classes") or meta["config"]["labels"]
        assert card["classes"] == classes, name
        # the input size the file stores, as the card says it
        if "input_size" in meta and meta.get("rig") != "any":  # weights for any rig: each rig's own size
            h, w = meta["input_size"]
            assert f"{w}x{h}" in card["input"], name
        else:
            assert f"{meta['config']['input_width']} px" in card["input"], name
        for data in card["training_data"]:
            assert data["license"] and data["source"] and data["description"], name
        # a non-commercial license in the training data reaches the file, and is said plainly
        if any("NC" in d["license"] for d in card["training_data"]):
            assert "non-commercial" in card["license"]["weights"].lower(), name
            assert "non-commercial" in card["license"]["use"].lower(), name
        assert all(s["command"].strip() and s["values"] for s in card["scores"]), name
        assert card["training"]["command"].strip(), name


def test_the_shipped_segmenter_cards_say_their_data_and_licenses():
    card = read_card(WEIGHTS_DIR / "segmenter.safetensors")
    real = [d for d in card["training_data"] if d["kind"] == "real"]
    assert [d["license"].split(" (")[0] for d in real] == ["Apache-2.0", "CC BY-NC 4.0"]
    assert "ImageNet" in real[0]["name"] and "CamVid" in real[1]["name"]
    assert "non-commercial" in card["license"]["weights"] and "segmenter:=open" in card["license"]["use"]
    camvid = {k: v for s in card["scores"] if "CamVid test" in s["data"] for k, v in s["values"].items()}
    assert camvid["road"] == 92.78 and camvid["mean"] == 69.88
    cfg = load_segmenter(WEIGHTS_DIR / "segmenter.safetensors").config
    assert (cfg.encoder, cfg.input_width, cfg.width_mult, cfg.depth_mult, cfg.encoder_stages) == ("lite", 480, 1.0, 1.0, 7)
    # the open one: nothing non-commercial in its training data, and it says so
    card = read_card(WEIGHTS_DIR / "segmenter_open.safetensors")
    assert all("NC" not in d["license"] for d in card["training_data"])
    assert card["license"]["weights"] == "Apache-2.0" and "CamVid" not in [d["name"][:6] for d in card["training_data"]]
    # the former default, kept as the other RGB methods' trunk
    cfg = load_segmenter(WEIGHTS_DIR / "segmenter_w320.safetensors").config
    assert (cfg.encoder, cfg.input_width, cfg.depth_mult) == ("efficientnet", 320, 0.5)


def _card(classes) -> dict:
    return {"card_version": 1, "summary": "tiny", "input": "96 px wide RGB", "classes": list(classes),
            "training_data": [{"name": "none", "kind": "synthetic", "description": "random init", "license": "Apache-2.0",
                               "source": "torch.manual_seed(0)"}],
            "license": {"weights": "Apache-2.0", "use": "tests only"},
            "training": {"command": "none", "details": "untrained"},
            "scores": [{"data": "none", "metric": "none", "values": {"x": 0.0, "y": 1}, "command": "none"}]}


@pytest.fixture
def tiny_segmenter(tmp_path):
    torch.manual_seed(0)
    model = Segmenter(SegmenterConfig(input_width=96, width_mult=0.25, depth_mult=0.25, encoder_stages=4,
                                      decoder_channels=16))
    return save_segmenter(model, tmp_path / "seg.safetensors", rig_name="tiny"), model


def test_set_card_rewrites_the_header_only(tiny_segmenter, tmp_path):
    path, model = tiny_segmenter
    before, (entries, meta, n) = path.read_bytes(), read_header(path)
    card = _card(model.config.labels)
    assert set_card(path, card)["tensors"] == len(model.state_dict())
    after = path.read_bytes()
    entries2, meta2, n2 = read_header(path)
    assert entries2 == entries and after[8 + n2:] == before[8 + n:]  # tensor entries and bytes as they were
    assert meta2 == {**meta, "card": card} and read_card(path) == card
    assert list(meta2["card"]["scores"][0]["values"]) == ["x", "y"]  # the order written is kept
    a, b = load_file(str(path)), model.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    loaded = load_segmenter(path).state_dict()
    assert all(torch.equal(loaded[k], b[k]) for k in b)
    # a malformed card or another file's classes: refused, the file untouched
    with pytest.raises(CardError, match="must be a finite number"):
        set_card(path, {**card, "scores": [{**card["scores"][0], "values": {"x": "high"}}]})
    with pytest.raises(CardError, match="differ from the weights' classes"):
        set_card(path, _card(("road", "vehicle")))
    assert path.read_bytes() == after and not list(tmp_path.glob("*.tmp"))


def test_the_command_line(tiny_segmenter, tmp_path, capsys):
    path, model = tiny_segmenter
    assert main(["show", str(path)]) == 1 and "has no model card" in capsys.readouterr().err
    card_file = tmp_path / "card.json"
    card_file.write_text(json.dumps(_card(model.config.labels)))
    assert main(["set", str(path), str(card_file)]) == 0 and "unchanged" in capsys.readouterr().out
    assert main(["show", str(path)]) == 0 and json.loads(capsys.readouterr().out)["summary"] == "tiny"
    card_file.write_text(json.dumps({**_card(model.config.labels), "license": "free"}))
    assert main(["set", str(path), str(card_file)]) == 2 and capsys.readouterr().err.startswith("error:")
    assert main(["check"]) == 0
    stale = tmp_path / "MODELS.md"
    stale.write_text("# old\n")
    assert main(["check", "--page", str(stale)]) == 1 and "differs" in capsys.readouterr().err
    assert main(["write", "--out", str(stale)]) == 0 and stale.read_text() == MODELS_MD.read_text()
