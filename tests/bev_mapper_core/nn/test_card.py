"""Model cards in weights files (bev_mapper_core/nn/card.py): the schema check names the bad
field, and every weights reader accepts a document with a card and with keys it does not know,
and refuses a malformed card or one whose classes are not the file's."""

from __future__ import annotations

import copy
import json

import pytest
from safetensors.torch import load_file, save_file

from bev_mapper_core.methods import WEIGHTS_DIR
from bev_mapper_core.methods.bimapper.weights import WeightsFile
from bev_mapper_core.methods.focusbev.weights import FOCUSBEV_WEIGHTS
from bev_mapper_core.methods.s2g2.weights import read_s2g2_metadata
from bev_mapper_core.methods.segmenter.weights import load_segmenter, read_segmenter_metadata
from bev_mapper_core.nn.card import MAX_TEXT, CardError, check_card, check_card_fits
from bev_mapper_core.nn.weights import META_KEY, WeightsError


def good_card(classes=("road", "vehicle")) -> dict:
    return {
        "card_version": 1, "summary": "a test model", "input": "64x40 label images", "classes": list(classes),
        "training_data": [{"name": "drives", "kind": "synthetic", "description": "seeds 0-1", "license": "Apache-2.0",
                           "source": "bev_mapper_core.synth"}],
        "license": {"weights": "Apache-2.0", "use": "any"},
        "training": {"command": "bev-train ...", "details": "2 steps"},
        "scores": [{"data": "drive 9", "metric": "IoU %", "values": {"road": 90.5, "mIoU": 45}, "command": "bev-train eval"}],
    }


def _spoil(card: dict, path: tuple, value) -> dict:
    card = copy.deepcopy(card)
    obj = card
    for key in path[:-1]:
        obj = obj[key]
    if value is KeyError:
        del obj[path[-1]]
    else:
        obj[path[-1]] = value
    return card


@pytest.mark.parametrize(("path", "value", "message"), [
    (("summary",), KeyError, "lacks \\['summary'\\]"),
    (("summary",), "  ", "card.summary must be a non-empty string"),
    (("summary",), "x" * (MAX_TEXT + 1), "longer than"),
    (("card_version",), 2, "this code reads 1"),
    (("card_version",), True, "must be an integer"),
    (("classes",), [], "1..64 items"),
    (("classes", 0), 3, r"card.classes\[0\]"),
    (("training_data",), "synthetic", "must be a list"),
    (("training_data", 0, "kind"), "scraped", "must be one of"),
    (("training_data", 0, "license"), KeyError, "lacks \\['license'\\]"),
    (("license",), "Apache-2.0", "card.license must be an object"),
    (("license", "use"), KeyError, "lacks \\['use'\\]"),
    (("training", "command"), None, "training.command must be a non-empty string"),
    (("scores", 0, "values"), {}, "1..64 named numbers"),
    (("scores", 0, "values", "road"), "high", "must be a finite number"),
    (("scores", 0, "values", "road"), float("nan"), "must be a finite number"),
    (("scores", 0, "values", "road"), True, "must be a finite number"),
    (("scores", 0, "command"), KeyError, "lacks \\['command'\\]"),
    (("scores", 0, "note"), 5, "note must be a non-empty string"),
])
def test_a_malformed_card_is_refused_naming_the_field(path, value, message):
    assert check_card(good_card()) is not None
    with pytest.raises(CardError, match=message):
        check_card(_spoil(good_card(), path, value))


def test_a_card_may_carry_keys_this_version_does_not_know():
    card = {**good_card(), "later_field": {"anything": 1}}
    card["scores"][0]["note"] = "an optional note"
    assert check_card(card) is card
    with pytest.raises(CardError, match="must be an object"):
        check_card(["not", "a", "card"])


def test_the_cards_classes_must_be_the_files():
    check_card_fits(good_card(), {"classes": ["road", "vehicle"]})
    check_card_fits(good_card(("unlabeled", "road")), {"config": {"labels": ["unlabeled", "road"]}})
    check_card_fits(good_card(), {})  # a document without classes: nothing to compare
    with pytest.raises(CardError, match="differ from the weights' classes"):
        check_card_fits(good_card(), {"classes": ["vehicle", "road"]})


def _rewrite(src, dst, change) -> None:
    """``src`` written to ``dst`` with its document changed by ``change(doc)`` (tensors as they are)."""
    from safetensors import safe_open
    with safe_open(str(src), framework="pt") as f:
        doc = json.loads(f.metadata()[META_KEY])
    doc.pop("card", None)
    change(doc)
    save_file(load_file(str(src)), str(dst), metadata={META_KEY: json.dumps(doc)})


READERS = {
    "segmenter.safetensors": read_segmenter_metadata,
    "bimapper_front1_labels.safetensors": lambda p: WeightsFile.open(p).meta,
    "s2g2_front1_rgb.safetensors": read_s2g2_metadata,
    "focusbev_front1_rgb.safetensors": FOCUSBEV_WEIGHTS.read_metadata,
}


@pytest.mark.parametrize("name", sorted(READERS))
def test_every_reader_accepts_a_card_and_unknown_keys_and_refuses_a_bad_card(tmp_path, name):
    read = READERS[name]

    def classes_of(doc):
        return doc["classes"] if "classes" in doc else doc["config"]["labels"]

    plain = tmp_path / "plain.safetensors"  # no card at all: still read
    _rewrite(WEIGHTS_DIR / name, plain, lambda doc: None)
    assert "card" not in read(plain)

    ok = tmp_path / "ok.safetensors"
    _rewrite(WEIGHTS_DIR / name, ok, lambda doc: doc.update(card=good_card(classes_of(doc)), from_the_future={"x": 1}))
    meta = read(ok)
    assert meta["card"]["summary"] == "a test model" and meta["from_the_future"] == {"x": 1}

    bad = tmp_path / "bad.safetensors"
    _rewrite(WEIGHTS_DIR / name, bad, lambda doc: doc.update(card=_spoil(good_card(classes_of(doc)),
                                                                          ("scores", 0, "values", "road"), "high")))
    with pytest.raises(WeightsError, match="bad model card .*must be a finite number"):
        read(bad)

    other = tmp_path / "other.safetensors"
    _rewrite(WEIGHTS_DIR / name, other, lambda doc: doc.update(card=good_card(list(reversed(classes_of(doc))))))
    with pytest.raises(WeightsError, match="bad model card .*differ from the weights' classes"):
        read(other)


def test_a_segmenter_with_a_card_and_unknown_keys_loads_as_without(tmp_path):
    ok = tmp_path / "ok.safetensors"
    _rewrite(WEIGHTS_DIR / "segmenter.safetensors", ok,
             lambda doc: doc.update(card=good_card(doc["config"]["labels"]), from_the_future=[1, 2]))
    a, b = load_segmenter(ok).state_dict(), load_segmenter(WEIGHTS_DIR / "segmenter.safetensors").state_dict()
    assert a.keys() == b.keys() and all(a[k].equal(b[k]) for k in a)
