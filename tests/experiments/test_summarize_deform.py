"""summarize_deform: the by-kind table is the mean over scenes of each kind, per variant."""

import json

import pytest

from experiments.summarize_deform import by_kind, kind_of, main


def _rec(scene, edit, variant, psnr, ft=None):
    r = {"scene": scene, "edit": edit, "variant": variant,
         "zero_shot": {"psnr": psnr, "ssim": 0.5, "lpips": 0.1}}
    if ft is not None:
        r["finetune"] = {"psnr": ft, "ssim": 0.6, "lpips": None}
    return r


def test_means_by_kind_and_every_edit_has_a_kind(tmp_path):
    records = [_rec("stool", "twist", "full", 20.0, 21.0), _rec("cup", "bend", "full", 22.0, 23.0),
               _rec("cup", "delete_handle", "full", 18.0, 19.0), _rec("cup", "bend", "no_ist", 10.0, 11.0)]
    table = by_kind(records).splitlines()
    assert table[0] == "| variant | smooth deformation | deletion | mean | SSIM | LPIPS |"
    assert table[2] == "| full | 21.00 | 18.00 | 20.00 | 0.500 | 0.100 |"
    assert table[3] == "| no_ist | 10.00 |  | 10.00 | 0.500 | 0.100 |"
    assert "| full | 22.00 | 19.00 | 21.00 | 0.600 |  |" in by_kind(records, "finetune")
    with pytest.raises(KeyError, match="has no kind"):
        kind_of("squash")
    path = tmp_path / "deform_benchmark_x.json"
    path.write_text(json.dumps({"preset": "x", "commit": "abc", "records": records,
                                "unedited": {"cup": {"psnr": 24.0}, "stool": {"psnr": 22.0}}}))
    main([str(path)])
    text = (tmp_path / "deform_benchmark_x_by_kind.md").read_text()
    assert "**Fine-tuned**" in text and "23.00 dB on their own test views" in text
