"""`xmetro export-default` (issue 16): never overwrites the packaged model unless asked; its card records the
scanner, a data-hashed id and the command that made it."""

from __future__ import annotations

import hashlib
import json

import pytest

from xmetro_ros.apps.cli import main
from xmetro_ros.scan.resources import default_model_dir


def _digest(d) -> str:
    h = hashlib.sha256()
    for f in sorted(d.iterdir()):
        h.update(f.name.encode() + f.read_bytes())
    return h.hexdigest()


def test_export_default_needs_a_target_and_writes_a_traceable_card(tmp_path, capsys):
    packaged = _digest(default_model_dir())
    with pytest.raises(SystemExit) as e:  # neither --out nor --replace-packaged: refused by the parser
        main(["export-default", "--profile", "micro"])
    assert e.value.code == 2 and "--out" in capsys.readouterr().err
    for seed in (0, 1):
        assert main(["export-default", "--profile", "micro", "--seed", str(seed), "--no-calibrate",
                     "--out", str(tmp_path / f"m{seed}")]) in (0, None)
    cards = [json.loads((tmp_path / f"m{s}" / "card.json").read_text()) for s in (0, 1)]
    for seed, card in enumerate(cards):
        assert card["trained_by"] == f"xmetro export-default --profile micro --seed {seed}"
        assert card["scanner"]["id"] == "xm-ls90"
        assert card["id"].startswith(f"pointnet_multi-micro-s{seed}-") and len(card["id"].rsplit("-", 1)[1]) >= 6
    assert cards[0]["id"] != cards[1]["id"]  # other data, another id
    assert _digest(default_model_dir()) == packaged  # the packaged model untouched
