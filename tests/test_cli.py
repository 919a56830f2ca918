import json

import numpy as np

from jaxreg.cli import main


def test_demo_json_report(capsys, tmp_path):
    assert main(["demo", "--json", "--out", str(tmp_path)]) == 0
    report = json.loads(capsys.readouterr().out)
    for key in (
        "pose",
        "failed_stage",
        "reason",
        "stages",
        "inlier_rmse_mm",
        "inlier_fraction",
        "predicted_grasp_success",
        "translation_error_mm",
        "rotation_error_deg",
        "add_s_mm",
    ):
        assert key in report
    pose = np.array(report["pose"])
    assert pose.shape == (4, 4) and np.allclose(pose[3], [0, 0, 0, 1])
    assert report["failed_stage"] is None
    assert report["rotation_error_deg"] < 1.0 and report["translation_error_mm"] < 2.0
    # the single start outside the basin is confidently wrong, which the demo shows
    assert report["stages"]["register"]["single_start_from_centroid"]["rotation_error_deg"] > 20
    assert json.loads((tmp_path / "demo.json").read_text()) == report


def test_bad_command_line_is_one_clear_error(capsys):
    try:
        main(["nonsense"])
    except SystemExit as exit_:
        assert exit_.code != 0
    assert "invalid choice" in capsys.readouterr().err
