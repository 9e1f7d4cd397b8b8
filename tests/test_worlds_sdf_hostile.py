"""Issue 55: `curlnav worlds import-sdf` under hostile SDF files and output paths. Each ends in one
``curlnav: error:`` line naming the file and the limit, exit 2, nothing written, within seconds
and 500 MB (the CLI in a subprocess whose address space is capped)."""

from __future__ import annotations

import time

import pytest
from conftest import assert_one_line_error, run_capped
from test_worlds_sdf import box, cylinder, sdf

from curlnav.cli import main
from curlnav.worlds.real.sdf import SdfError, world_from_sdf

MESH = ("<model name='{name}'><static>1</static><link name='l'><collision name='c'><geometry><mesh><uri>m.dae</uri>"
        "</mesh></geometry></collision></link></model>")


def refused_fast(tmp_path, *args: str, fragments: tuple[str, ...]) -> str:
    """Run import-sdf capped; assert one line holding ``fragments``, exit 2, under 500 MB and 20 s
    (generous: a loaded 2-core CI), and no world file or image under ``tmp_path``; the line."""
    before = {p for p in tmp_path.rglob("*")}
    began = time.perf_counter()
    result, peak_mb, _ = run_capped("worlds", "import-sdf", *args)
    elapsed = time.perf_counter() - began
    line = assert_one_line_error(result, *fragments)
    assert elapsed < 20 and peak_mb < 500, (elapsed, peak_mb)
    assert {p for p in tmp_path.rglob("*")} == before, "something was written"
    return line


@pytest.mark.slow
def test_models_nested_past_the_bound_are_refused_in_one_line(tmp_path):
    path = sdf(tmp_path, "<model name='m'><static>1</static>" * 2000 + box("b", "0 0 0.5 0 0 0", "1 1 1")
               + "</model>" * 2000)
    refused_fast(tmp_path, str(path), "--out", str(tmp_path / "w.yaml"), fragments=(str(path), "nested", "32"))


@pytest.mark.slow
def test_more_collisions_than_the_bound_are_refused_before_rasterising(tmp_path):
    many = "".join(cylinder(f"c{i}", f"{i % 100 * 0.2} {i // 100 * 0.2} 0.5 0 0 0", 0.075) for i in range(20_001))
    refused_fast(tmp_path, str(sdf(tmp_path, many)), "--out", str(tmp_path / "w.yaml"), fragments=("20000",))


@pytest.mark.slow
def test_shapes_covering_too_many_cells_are_refused_before_rasterising(tmp_path):
    # 1000 copies of a 120 m box: a 182 KB file that ran past 120 s
    path = sdf(tmp_path, "".join(box(f"b{i}", "0 0 0.5 0 0 0", "120 120 1") for i in range(1000)))
    refused_fast(tmp_path, str(path), "--out", str(tmp_path / "w.yaml"), fragments=(str(path), "50 million"))


@pytest.mark.slow
def test_a_grid_near_the_cap_rasterises_in_bounded_memory(tmp_path):
    # a 120 m box at 0.025 m: 23 million cells, under the 25 million cap (it took 824 MB at once)
    path = sdf(tmp_path, box("b", "0 0 0.5 0 0 0", "120 120 1"))
    began = time.perf_counter()
    result, peak_mb, _ = run_capped("worlds", "import-sdf", str(path), "--out", str(tmp_path / "w.yaml"))
    assert result.returncode == 0, result.stderr
    assert time.perf_counter() - began < 20 and peak_mb < 500, peak_mb
    assert "1 boxes and 0 cylinders" in result.stdout


@pytest.mark.slow
def test_an_sdf_file_above_the_size_cap_is_refused_unread(tmp_path):
    path = sdf(tmp_path, box("b", "0 0 0.5 0 0 0", "1 1 1") + "<!--" + "x" * (8 << 20) + "-->")
    refused_fast(tmp_path, str(path), "--out", str(tmp_path / "w.yaml"), fragments=(str(path), "8192 KiB"))


@pytest.mark.slow
def test_a_doctype_and_its_entities_are_refused(tmp_path):
    # an 8 MB file whose entity expands 30-fold (under expat's own amplification bound) into a model name
    path = tmp_path / "e.world"
    path.write_text("<?xml version='1.0'?><!DOCTYPE sdf [<!ENTITY e '" + "x" * 90 + "'>]><sdf><world>"
                    + MESH.format(name="&e;" * 2_700_000) + "</world></sdf>")
    refused_fast(tmp_path, str(path), "--out", str(tmp_path / "w.yaml"), fragments=(str(path), "DOCTYPE"))


def test_a_shape_beyond_float_range_is_refused_in_one_line(tmp_path):
    for models in (box("b", "0 0 0.5 0 0 0", "1e308 1e308 1"), box("b", "1e308 0 0.5 0 0 0", "1 1 1")
                   + box("c", "-1e308 0 0.5 0 0 0", "1 1 1")):
        with pytest.raises(SdfError, match="beyond 100000 m"):
            world_from_sdf(sdf(tmp_path, models))


def run_main(capsys, *args: str) -> tuple[int, list[str], str]:
    """``curlnav ARGS`` in this process: (exit code, stderr lines, stdout)."""
    rc = main(list(args))
    captured = capsys.readouterr()
    return rc, captured.err.splitlines(), captured.out


def test_out_naming_a_folder_is_refused_before_any_work(tmp_path, capsys):
    path = sdf(tmp_path, box("b", "0 0 0.5 0 0 0", "1 1 1"))
    (tmp_path / "w.yaml").mkdir()
    rc, err, _ = run_main(capsys, "worlds", "import-sdf", str(path), "--out", str(tmp_path / "w.yaml"))
    assert rc == 2 and len(err) == 1 and "is a folder" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.world", "w.yaml"]


@pytest.mark.parametrize("under", ["a_file/w.yaml", "a_file/deeper/w.yaml"])
def test_out_under_a_file_is_refused_before_any_work(tmp_path, capsys, under):
    path = sdf(tmp_path, box("b", "0 0 0.5 0 0 0", "1 1 1"))
    (tmp_path / "a_file").write_text("x")
    rc, err, _ = run_main(capsys, "worlds", "import-sdf", str(path), "--out", str(tmp_path / under))
    assert rc == 2 and len(err) == 1 and "not a folder" in err[0] and "a_file" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "w.world"]


@pytest.mark.parametrize("name", ["x.yaml", "x.pgm"])
def test_the_input_is_never_overwritten_by_its_own_output(tmp_path, capsys, name):
    path = sdf(tmp_path, box("b", "0 0 0.5 0 0 0", "1 1 1"), name=name)
    text = path.read_text()
    rc, err, _ = run_main(capsys, "worlds", "import-sdf", str(path))
    assert rc == 2 and len(err) == 1 and "overwrite the input" in err[0] and "--out" in err[0], err
    assert path.read_text() == text and [p.name for p in tmp_path.iterdir()] == [name]


def test_a_failed_write_leaves_nothing_behind(tmp_path, capsys, monkeypatch):
    import curlnav.worlds.core.world as world_module

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")  # the image written, then the disk fills

    monkeypatch.setattr(world_module.yaml, "safe_dump", full_disk)
    path = sdf(tmp_path, box("b", "0 0 0.5 0 0 0", "1 1 1"))
    rc, err, _ = run_main(capsys, "worlds", "import-sdf", str(path), "--out", str(tmp_path / "new" / "w.yaml"))
    assert rc == 2 and len(err) == 1 and "No space left" in err[0], err
    assert [p.name for p in tmp_path.iterdir()] == ["w.world"]


def test_the_skipped_line_is_bounded_in_names_and_items(tmp_path, capsys):
    meshes = MESH.format(name="m" * 1_000_000) + "".join(MESH.format(name=f"mesh{i}") for i in range(50))
    path = sdf(tmp_path, box("b", "0 0 0.5 0 0 0", "1 1 1") + meshes)
    rc, err, out = run_main(capsys, "worlds", "import-sdf", str(path), "--out", str(tmp_path / "w.yaml"),
                            "--skip-unsupported")
    assert rc == 0, err
    skipped = out.splitlines()[-1]
    assert skipped.startswith("skipped 51 unsupported: mesh 'mmmm") and "and 41 more" in skipped, skipped[:300]
    assert len(skipped) < 1000, len(skipped)


@pytest.mark.parametrize("models, fragment", [
    ("<model name='{n}'><pose>1 2</pose></model>", "malformed pose"),
    ("<model name='{n}'><pose relative_to='{n}'>0 0 0 0 0 0</pose></model>", "relative to frame"),
    ("<model name='{n}'><static>1</static><link name='l'><collision name='c'><geometry><box><size>1 -1 1</size>"
     "</box></geometry></collision></link></model>", "<size>"),
    (MESH.replace("{name}", "{n}") * 3, "cannot represent"),
])
def test_errors_naming_a_long_model_name_stay_short(tmp_path, models, fragment):
    path = sdf(tmp_path, box("b", "0 0 0.5 0 0 0", "1 1 1") + models.replace("{n}", "n" * 100_000))
    with pytest.raises(SdfError, match=fragment) as caught:
        world_from_sdf(path)
    assert len(str(caught.value)) < len(str(path)) + 400, len(str(caught.value))
