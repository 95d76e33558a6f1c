"""segmentation.config: the settings removed after they measured as no-ops or losses are named as removed,
and configs saved before their removal still read."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from segmentation.config import SegTrainConfig
from tests.tiny_nets import SEG_TINY_SEMI
from u4d_aug.config import config_to_dict, load_config, saved_config, without_removed_keys
from u4d_aug.errors import InputError


def semi_config(root: Path, out: Path, *overrides: str) -> SegTrainConfig:
    return load_config(SegTrainConfig, SEG_TINY_SEMI, [f"data.root={root}", f"out_dir={out}", *overrides])


@pytest.mark.parametrize(
    ("override", "why"),
    [("semi.teacher_views=4", "mirror views changed nothing"), ("semi.burn_in_teacher=ema", "Unbiased Teacher"),
     ("optim.restart_step=700", "warm restart"), ("optim.restart_lr=0.005", "warm restart"),
     ("loss.point_fraction=0.25", "lost 7 mIoU points")],
)  # fmt: skip
def test_a_removed_setting_is_a_one_line_error_that_says_so(toy_root, tmp_path, override, why):
    key = override.partition("=")[0]
    with pytest.raises(InputError, match=f"config key '{re.escape(key)}' was removed \\(.*{why}") as caught:
        semi_config(toy_root, tmp_path, override)
    assert "\n" not in str(caught.value) and "delete it" in str(caught.value)


def test_a_saved_config_with_removed_keys_at_their_off_values_still_reads(toy_root, tmp_path):
    """A checkpoint's or config.yaml's config from before the keys were removed: read without them; a removed
    setting that acted is named in a warning."""
    cfg = semi_config(toy_root, tmp_path)
    old = config_to_dict(cfg)
    old["semi"] |= {"teacher_views": 1, "burn_in_teacher": "copy"}
    old["optim"] |= {"restart_step": 0, "restart_lr": None}
    old["loss"]["point_fraction"] = 1.0
    assert saved_config(SegTrainConfig, old, "old.pt") == cfg
    assert without_removed_keys(SegTrainConfig, old)[1] == {}
    old["semi"]["teacher_views"] = 4
    assert without_removed_keys(SegTrainConfig, old)[1] == {"semi.teacher_views": 4}
    with pytest.warns(UserWarning, match="old.pt: trained with semi.teacher_views=4, a setting since removed"):
        assert saved_config(SegTrainConfig, old, "old.pt") == cfg
