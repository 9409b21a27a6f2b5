import json

import numpy as np
import pytest
from PIL import Image

from keygen.cli.main import main
from keygen.objects.asset import Asset


def run(capsys, *argv) -> tuple[int, str]:
    code = main(list(argv))
    out = capsys.readouterr().out.strip().splitlines()
    return code, out


def test_generate_writes_one_folder_per_instance_and_resumes(tmp_path, capsys):
    out = tmp_path / "mugs"
    code, lines = run(
        capsys,
        "objects",
        "generate",
        "--category",
        "mug",
        "--split",
        "test",
        "--count",
        "3",
        "--seed",
        "0",
        "--out",
        str(out),
    )
    assert code == 0
    summary = json.loads(lines[-1])
    assert summary["count"] == 3 and summary["written"] == 3
    folders = sorted(p.name for p in out.iterdir())
    assert folders == ["mug-test-000", "mug-test-001", "mug-test-002"]
    meta = json.loads((out / "mug-test-001" / "meta.json").read_text())
    assert {"category", "instance_id", "params", "scale", "anchors", "bbox"} <= set(meta)
    assert (out / "mug-test-001" / "visual.obj").is_file()
    assert any((out / "mug-test-001" / "collision").iterdir())
    # a rerun keeps what is there; a lost instance is rebuilt
    import shutil

    shutil.rmtree(out / "mug-test-002")
    code, lines = run(
        capsys,
        "objects",
        "generate",
        "--category",
        "mug",
        "--split",
        "test",
        "--count",
        "3",
        "--out",
        str(out),
    )
    summary = json.loads(lines[-1])
    assert summary["kept"] == 2 and summary["written"] == 1


def test_generate_with_scale_and_validate(tmp_path, capsys):
    out = tmp_path / "bowls"
    code, lines = run(
        capsys,
        "objects",
        "generate",
        "--category",
        "bowl",
        "--split",
        "policy",
        "--count",
        "1",
        "--scale",
        "0.7",
        "--out",
        str(out),
    )
    assert code == 0
    asset = Asset.load(out / "bowl-policy-000")
    assert asset.scale == pytest.approx(0.7)
    code, lines = run(capsys, "objects", "validate", str(out))
    assert code == 0 and json.loads(lines[-1]) == {"checked": 1, "failed": 0}


def test_validate_flags_a_misplaced_anchor(tmp_path, capsys):
    out = tmp_path / "knives"
    run(
        capsys,
        "objects",
        "generate",
        "--category",
        "knife",
        "--split",
        "test",
        "--count",
        "1",
        "--out",
        str(out),
    )
    meta_file = out / "knife-test-000" / "meta.json"
    meta = json.loads(meta_file.read_text())
    meta["anchors"]["blade_tip"]["value"] = [0.0, 0.0, 0.05]
    meta_file.write_text(json.dumps(meta))
    code, lines = run(capsys, "objects", "validate", str(out))
    assert code == 1 and json.loads(lines[-1])["failed"] == 1


def test_preview_writes_a_contact_sheet(tmp_path, capsys):
    out = tmp_path / "knives"
    run(
        capsys,
        "objects",
        "generate",
        "--category",
        "knife",
        "--split",
        "train",
        "--count",
        "2",
        "--out",
        str(out),
    )
    code, lines = run(
        capsys, "objects", "preview", str(out), "--out", str(tmp_path / "grid.png"), "--tile", "64"
    )
    assert code == 0
    img = np.asarray(Image.open(tmp_path / "grid.png"))
    assert img.shape[1] == 6 * 64 and img.std() > 5


def test_import_cli_round_trip_and_errors(tmp_path, capsys):
    from keygen.objects.importer import export_for_import
    from keygen.objects.splits import make_instance

    asset = make_instance("bowl", "test", 0)
    mesh_path, anchors_path = export_for_import(asset, tmp_path / "export", units="mm")
    code, lines = run(
        capsys,
        "objects",
        "import",
        str(mesh_path),
        "--category",
        "bowl",
        "--anchors",
        str(anchors_path),
        "--collision",
        "hull",
        "--out",
        str(tmp_path / "imported"),
    )
    assert code == 0, lines
    summary = json.loads(lines[-1])
    assert summary["anchors"] and summary["collision_parts"] == 1
    loaded = Asset.load(tmp_path / "imported")
    np.testing.assert_allclose(loaded.bbox, asset.bbox, atol=1e-5)
    np.testing.assert_allclose(loaded.anchor("rim_grasp"), asset.anchor("rim_grasp"), atol=1e-6)
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    assert main(["objects", "import", str(empty), "--category", "mug", "--out", str(tmp_path / "bad")]) == 2
    assert "error" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_bad_arguments_exit_with_a_message(tmp_path, capsys):
    assert (
        main(
            [
                "objects",
                "generate",
                "--category",
                "mug",
                "--split",
                "test",
                "--count",
                "0",
                "--out",
                str(tmp_path),
            ]
        )
        == 2
    )
    assert "--count" in capsys.readouterr().err
    assert main(["objects", "preview", str(tmp_path / "nothing"), "--out", str(tmp_path / "x.png")]) == 2
