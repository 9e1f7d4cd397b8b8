"""`curlnav worlds import-sdf`: Gazebo worlds written by hand, and the BARN Challenge's 300 worlds
against their own cylinder lattice and reference paths."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest
from conftest import assert_one_line_error, run_curlnav
from scipy import ndimage

from curlnav.worlds.barn_challenge import barn
from curlnav.worlds.core.world import load_world
from curlnav.worlds.real.sdf import SdfError, world_from_sdf

GROUND = """<model name='ground_plane'><static>1</static><link name='link'><collision name='collision'>
<geometry><plane><normal>0 0 1</normal><size>100 100</size></plane></geometry></collision></link></model>"""


def sdf(tmp_path, models: str, name: str = "w.world"):
    path = tmp_path / name
    path.write_text(f"<?xml version='1.0'?><sdf version='1.6'><world name='default'>{GROUND}{models}</world></sdf>")
    return path


def box(name: str, pose: str, size: str, static: bool = True, link_pose: str = "", collision_pose: str = "") -> str:
    lp = f"<pose>{link_pose}</pose>" if link_pose else ""
    cp = f"<pose>{collision_pose}</pose>" if collision_pose else ""
    return (f"<model name='{name}'><static>{int(static)}</static><pose frame=''>{pose}</pose><link name='link'>{lp}"
            f"<collision name='collision'>{cp}<geometry><box><size>{size}</size></box></geometry></collision>"
            f"<visual name='visual'><geometry><box><size>{size}</size></box></geometry></visual></link></model>")


def cylinder(name: str, pose: str, radius: float, length: float = 1.0) -> str:
    return (f"<model name='{name}'><static>1</static><pose>{pose}</pose><link name='link'><collision name='c'>"
            f"<geometry><cylinder><radius>{radius}</radius><length>{length}</length></cylinder></geometry>"
            f"</collision></link></model>")


MESH = ("<model name='house'><static>1</static><link name='link'><collision name='collision'><geometry><mesh>"
        "<uri>model://house/meshes/house.dae</uri></mesh></geometry></collision></link></model>")


def occupied(world, points) -> list[bool]:
    return [world.is_occupied(x, y) for x, y in points]


def test_a_box_becomes_its_cells(tmp_path):
    world, contents = world_from_sdf(sdf(tmp_path, box("b", "1 2 0.5 0 0 0", "1.0 0.5 1")))
    assert [s.kind for s in contents.shapes] == ["box"] and not contents.unsupported
    assert occupied(world, [(1, 2), (1.48, 2.23), (0.52, 1.77)]) == [True] * 3
    assert occupied(world, [(1.53, 2), (1, 2.28), (0.47, 1.77)]) == [False] * 3
    assert world.occupancy.sum() == pytest.approx(1.0 * 0.5 / world.resolution ** 2, rel=0.01)


def test_a_rotated_box_turns_with_its_yaw(tmp_path):
    world, _ = world_from_sdf(sdf(tmp_path, box("b", f"0 0 0 0 0 {math.pi / 4}", "2 0.2 1")))
    along = [(0.65, 0.65), (-0.65, -0.65)]  # on the long axis, 0.92 m from the centre
    assert occupied(world, along) == [True, True]
    assert occupied(world, [(0.9, 0.0), (0.0, 0.9), (0.75, 0.75)]) == [False] * 3


def test_a_box_on_its_side_keeps_its_upright_footprint(tmp_path):
    # rolled 90 degrees: its 2 m height lies along y, 0.4 m deep in z -> a 1 x 2 m footprint
    world, _ = world_from_sdf(sdf(tmp_path, box("b", f"0 0 0.2 {math.pi / 2} 0 0", "1 0.4 2")))
    assert occupied(world, [(0.45, 0.95), (-0.45, -0.95)]) == [True, True]
    assert occupied(world, [(0.55, 0.0), (0.0, 1.05)]) == [False, False]


def test_a_cylinder_is_a_disc(tmp_path):
    world, contents = world_from_sdf(sdf(tmp_path, cylinder("c", "3 -1 0.5 0 0 0", 0.3)))
    assert contents.shapes[0].kind == "cylinder"
    assert occupied(world, [(3.0, -1.0), (3.27, -1.0), (3.0, -0.73), (3.18, -0.82)]) == [True] * 4
    assert occupied(world, [(3.33, -1.0), (3.0, -1.33), (3.23, -0.77)]) == [False] * 3


def test_nested_model_link_and_collision_poses_compose(tmp_path):
    # outer model at (2, 0) turned 90 deg; inner model 1 m along its x -> (2, 1), turned with it;
    # link 1 m along the inner y -> (1, 1); collision 0.5 m along the link's x -> (1, 1.5)
    inner = box("inner", "1 0 0 0 0 0", "0.2 0.2 1", link_pose="0 1 0 0 0 0", collision_pose="0.5 0 0 0 0 0")
    outer = f"<model name='outer'><static>1</static><pose>2 0 0 0 0 {math.pi / 2}</pose>{inner}</model>"
    world, contents = world_from_sdf(sdf(tmp_path, outer))
    (shape,) = contents.shapes
    assert shape.name == "outer/inner/link/collision"
    assert (shape.x, shape.y) == (pytest.approx(1.0), pytest.approx(1.5))
    assert occupied(world, [(1.0, 1.5), (1.08, 1.58)]) == [True, True]
    assert occupied(world, [(1.5, 1.5), (1.0, 1.0), (0.5, 1.5), (1.13, 1.5)]) == [False] * 4  # not the naive sums


def test_shapes_out_of_a_ground_robots_reach_and_the_state_snapshot_are_left_out(tmp_path):
    models = (cylinder("c", "0 0 0.5 0 0 0", 0.2) + box("underground", "5 0 -1 0 0 0", "1 1 1")
              + box("overhead", "-5 0 3 0 0 0", "1 1 1")
              + "<state world_name='default'><model name='c'><pose>9 9 0 0 0 0</pose></model></state>")
    world, contents = world_from_sdf(sdf(tmp_path, models))
    assert [s.name for s in contents.shapes] == ["c/link/c"] and not contents.unsupported
    assert world.bounds[2] < 2.0


@pytest.mark.slow
def test_import_sdf_writes_a_world_file_the_loader_reads(tmp_path):
    path = sdf(tmp_path, box("b", "1 2 0.5 0 0 0", "1.0 0.5 1") + cylinder("c", "-1 0 0.5 0 0 0", 0.075))
    result = run_curlnav("worlds", "import-sdf", str(path), "--out", str(tmp_path / "out" / "w.yaml"))
    assert result.returncode == 0, result.stderr
    assert "1 boxes and 1 cylinders" in result.stdout
    world = load_world(tmp_path / "out" / "w.yaml")
    assert occupied(world, [(1, 2), (-1, 0)]) == [True, True]
    assert occupied(world, [(0, 1), (-1, 0.1)]) == [False, False]


@pytest.mark.slow
def test_a_mesh_is_refused_in_one_line_naming_it(tmp_path):
    path = sdf(tmp_path, box("b", "1 2 0.5 0 0 0", "1 1 1") + MESH)
    line = assert_one_line_error(run_curlnav("worlds", "import-sdf", str(path), "--out", str(tmp_path / "w.yaml")),
                                 "mesh 'house/link/collision'", "--skip-unsupported")
    assert str(path) in line and not (tmp_path / "w.yaml").exists()


@pytest.mark.slow
def test_skip_unsupported_drops_and_names_what_it_cannot_represent(tmp_path):
    extra = (MESH + "<model name='hill'><static>1</static><link name='l'><collision name='c'><geometry><heightmap>"
             "<uri>file://h.png</uri></heightmap></geometry></collision></link></model>"
             + box("cart", "4 4 0.5 0 0 0", "1 1 1", static=False)
             + box("ramp", "6 6 0.5 0 0.3 0", "1 1 1")
             + "<model name='wall'><static>1</static><link name='l'><collision name='c'><geometry><plane><normal>1 0 0"
               "</normal></plane></geometry></collision></link></model><include><uri>model://table</uri></include>")
    path = sdf(tmp_path, box("b", "1 2 0.5 0 0 0", "1 1 1") + extra)
    with pytest.raises(SdfError, match="mesh 'house/link/collision', heightmap 'hill/l/c', box 'cart/link/collision'"):
        world_from_sdf(path)
    result = run_curlnav("worlds", "import-sdf", str(path), "--out", str(tmp_path / "w.yaml"), "--skip-unsupported")
    assert result.returncode == 0, result.stderr
    skipped = result.stdout.splitlines()[-1]
    for item in ("mesh 'house/link/collision'", "heightmap 'hill/l/c'", "'cart/link/collision' (its model is not static)",
                 "tilted box 'ramp/link/collision'", "plane 'wall/l/c' (not the ground)", "include 'model://table'"):
        assert item in skipped, (item, skipped)
    world = load_world(tmp_path / "w.yaml")
    assert occupied(world, [(1, 2), (4, 4)]) == [True, True]  # (4, 4) lies outside the map: blocked
    assert world.bounds[2] < 2.6 and world.bounds[3] < 3.6  # the map holds only the static box


@pytest.mark.slow
@pytest.mark.parametrize("text, fragment", [
    ("<sdf><world><model name='a'></world></sdf>", "not well-formed XML"),
    ("<robot name='r'/>", "root element is <robot>"),
    ("<sdf><world>" + box("b", "0 0 0 0 0", "1 1 1") + "</world></sdf>", "malformed pose"),
    ("<sdf><world>" + box("b", "0 0 0 0 0 0", "1 -1 1") + "</world></sdf>", "box 'b/link/collision' <size>"),
    ("<sdf><world>" + GROUND + "</world></sdf>", "no static box or cylinder"),
])
def test_a_malformed_file_is_refused_in_one_line(tmp_path, text, fragment):
    path = tmp_path / "bad.world"
    path.write_text(text)
    assert_one_line_error(run_curlnav("worlds", "import-sdf", str(path)), str(path), fragment)


def expected_grid(n: int, world) -> np.ndarray:
    """The BARN lattice drawn on ``world``'s grid: a cell is blocked when its centre lies within
    0.075 m of a lattice cylinder's centre (written here, apart from curlnav.worlds.real.sdf)."""
    rows, cols = world.occupancy.shape
    xs = world.origin[0] + (np.arange(cols) + 0.5) * world.resolution
    ys = world.origin[1] + (np.arange(rows) + 0.5) * world.resolution
    out = np.zeros((rows, cols), bool)
    for j, k in zip(*np.nonzero(barn.lattice(n))):
        cx, cy = -(k + 0.5) * 0.15, (j + 0.5) * 0.15
        out |= ((xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2) <= 0.075 ** 2 + 1e-12
    return out


@pytest.mark.slow
def test_every_barn_world_imports_to_its_own_cylinder_lattice(tmp_path):
    """All 300 vendored worlds: the files are the originals byte for byte (the manifest's sha256);
    import-sdf gives exactly the lattice's cylinders; the lattice leaves every cell of the
    challenge's own reference path free on its C-space grid (BARN's 2-cell inflation)."""
    manifest = dict(reversed(line.split("  ")) for line in (barn.DATA / "MANIFEST.sha256").read_text().splitlines())
    mismatched = []
    for n in range(barn.COUNT):
        raw = barn.world_file(n)
        assert hashlib.sha256(raw).hexdigest() == manifest[f"jackal_helper/worlds/BARN/world_{n}.world"], n
        path = tmp_path / f"world_{n}.world"
        path.write_bytes(raw)
        world, contents = world_from_sdf(path)
        assert not contents.unsupported and len(contents.shapes) == barn.lattice(n).sum(), n
        if not np.array_equal(world.occupancy, expected_grid(n, world)):
            mismatched.append(n)
        blocked = ndimage.binary_dilation(barn.grid(n), np.ones((5, 5), bool))
        cells = barn.path_cells(n)
        assert not blocked[cells[:, 0], cells[:, 1]].any(), f"world {n}: its reference path crosses the lattice"
        path.unlink()
    assert not mismatched, f"import-sdf differs from the lattice on worlds {mismatched}"


@pytest.mark.slow
def test_a_barn_world_through_the_command_line(tmp_path):
    path = tmp_path / "world_7.world"
    path.write_bytes(barn.world_file(7))
    result = run_curlnav("worlds", "import-sdf", str(path), "--out", str(tmp_path / "w7.yaml"))
    assert result.returncode == 0, result.stderr
    assert f"0 boxes and {barn.lattice(7).sum()} cylinders" in result.stdout
    world = load_world(tmp_path / "w7.yaml")
    assert np.array_equal(world.occupancy, expected_grid(7, world))
    suite_world = barn.world(7)  # the suite's world: the same cylinders on its own frame
    assert abs(int(suite_world.occupancy.sum()) - int(world.occupancy.sum())) == 0


def test_the_vendored_grids_have_the_barn_sets_published_difficulty():
    """BARN's five metrics on the 300 grids (in the path files' orientation) and their reference
    paths: the ranges recomputed from the BARN set (docs: difficulty metrics), to two decimals."""
    from curlnav.worlds.difficulty.metrics import barn_metrics

    metrics = np.array([barn_metrics(barn.grid(n), barn.path_cells(n)) for n in range(barn.COUNT)])
    published = {"distance": (1.18, 2.13, 6.96), "visibility": (2.92, 5.28, 12.16), "dispersion": (0.65, 4.51, 6.13),
                 "characteristic dimension": (0.73, 3.22, 14.77), "tortuosity": (1.00, 1.17, 1.71)}
    for column, (name, (low, median, high)) in zip(metrics.T, published.items()):
        assert (column.min(), np.median(column), column.max()) == (
            pytest.approx(low, abs=0.006), pytest.approx(median, abs=0.006), pytest.approx(high, abs=0.006)), name
    lengths = [len(barn.path_cells(n)) for n in range(barn.COUNT)]
    assert (min(lengths), max(lengths)) == (31, 47)  # "path lengths 31-47 cells"
