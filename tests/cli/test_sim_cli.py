import json

import imageio.v2 as imageio

from keygen.cli.main import main


def test_sim_render_writes_a_tiled_video(tmp_path, capsys):
    out = tmp_path / "stack.mp4"
    code = main(
        [
            "sim",
            "render",
            "--task",
            "stack",
            "--seed",
            "1",
            "--steps",
            "3",
            "--image-size",
            "48",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["frames"] == 4
    frames = [frame for frame in imageio.get_reader(out)]  # noqa: C416 (its len() is inf)
    assert len(frames) == 4 and frames[0].shape[:2] == (96, 96)  # 2 x 2 tiles of 48 px
    assert frames[-1].std() > 10


def test_sim_render_refuses_unknown_format(tmp_path, capsys):
    assert main(["sim", "render", "--task", "pour", "--out", str(tmp_path / "x.avi")]) == 2
    assert ".mp4" in capsys.readouterr().err
