"""Floors: MovingAI grid maps and JSON plans, the rectangle merge, reachability, warehouses."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import sim
from sim.floors import (
    _free_raster,
    check_reachable,
    grid_rectangles,
    load_floor,
    save_floor_json,
    warehouse_floor,
)

KIVA = [
    "..........",
    ".@@@@@@@@.",
    ".eeeeeeee.",
    "r........r",
    ".eeeeeeee.",
    ".@@@@@@@@.",
    "..........",
]


def _map_text(rows: list[str], height: int | None = None, width: int | None = None,
              kind: str = "octile") -> str:
    height = len(rows) if height is None else height
    width = len(rows[0]) if width is None else width
    return f"type {kind}\nheight {height}\nwidth {width}\nmap\n" + "\n".join(rows) + "\n"


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _plan(**fields: object) -> dict:
    plan = {"bounds": [0, 0, 4, 3], "shelves": [[1.0, 1.0, 3.0, 1.6]],
            "pickups": [[1.5, 0.8], [2.5, 1.8]], "stations": [[0.3, 2.7]],
            "depot": [[0.0, 0.0, 1.0, 0.6]]}
    plan.update(fields)
    return {k: v for k, v in plan.items() if v is not None}


def _covered(rects: np.ndarray, shape: tuple[int, int], cell: float) -> np.ndarray:
    """How many rectangles cover each cell's centre (row 0 at the top)."""
    H, W = shape
    count = np.zeros(shape, dtype=int)
    cx = (np.arange(W) + 0.5) * cell
    cy = (H - 1 - np.arange(H) + 0.5) * cell
    for x0, y0, x1, y1 in rects:
        count += ((cy[:, None] > y0) & (cy[:, None] < y1)) & ((cx > x0) & (cx < x1))[None, :]
    return count


# ---------------------------------------------------------------------- grid maps
def test_load_map_with_kiva_letters(tmp_path: Path) -> None:
    world = load_floor(_write(tmp_path, "kiva.map", _map_text(KIVA)), cell_size=0.5)
    assert world.bounds == (0.0, 0.0, 5.0, 3.5)
    assert world.is_floor and world.depot.shape == (0, 4)
    assert len(world.pickups) == 16 and len(world.stations) == 2
    # Row 0 is the top: the station row (map row 3) is the middle, y = (7 - 1 - 3 + 0.5) * 0.5.
    np.testing.assert_allclose(world.stations, [[0.25, 1.75], [4.75, 1.75]])
    # Pickups at the centres of their cells; map row 2 (upper) first.
    np.testing.assert_allclose(world.pickups[0], [0.75, 2.25])
    np.testing.assert_allclose(world.pickups[-1], [4.25, 1.25])
    # Two shelf rows of 8 cells each, one rectangle per row.
    np.testing.assert_allclose(world.obstacles, [[0.5, 2.5, 4.5, 3.0], [0.5, 0.5, 4.5, 1.0]])
    assert world.agent_radius == 0.15


def test_every_free_letter_is_free_and_every_blocked_one_blocks(tmp_path: Path) -> None:
    rows = ["e.GS.r", "@TOW..", "......"]
    world = load_floor(_write(tmp_path, "letters.map", _map_text(rows)))
    blocked = np.array([[c in "@TOW" for c in row] for row in rows])
    assert (_covered(world.obstacles, blocked.shape, 1.0) == blocked).all()
    assert len(world.obstacles) == 1  # @TOW is one run


def test_map_with_crlf_line_ends_and_trailing_blank_lines(tmp_path: Path) -> None:
    text = _map_text(KIVA).replace("\n", "\r\n") + "\r\n\r\n"
    path = tmp_path / "crlf.map"
    path.write_bytes(text.encode())
    assert len(load_floor(path, cell_size=0.5).pickups) == 16


def test_cell_size_scales_the_floor(tmp_path: Path) -> None:
    path = _write(tmp_path, "kiva.map", _map_text(KIVA))
    small, big = load_floor(path, cell_size=0.5), load_floor(path, cell_size=2.0)
    np.testing.assert_allclose(big.pickups, 4 * small.pickups)
    np.testing.assert_allclose(big.obstacles, 4 * small.obstacles)


def test_cell_exactly_one_agv_wide_is_enough(tmp_path: Path) -> None:
    # A corridor one cell (one AGV diameter) wide joins the pickup to the station.
    rows = ["@@@@@", "e...r", "@@@@@"]
    world = load_floor(_write(tmp_path, "corridor.map", _map_text(rows)), cell_size=0.3)
    check_reachable(world)  # the raster check agrees with the exact grid check
    with pytest.raises(ValueError, match=r"cell_size 0.29 is too small .* cell_size >= 0.3"):
        load_floor(tmp_path / "corridor.map", cell_size=0.29)


@pytest.mark.parametrize(("text", "match"), [
    ("", "line 1: expected the header 'type octile', got an empty line"),
    ("height 3\nwidth 3\nmap\n...\n", "line 1: expected the header 'type octile'"),
    ('{"bounds": [0, 0, 1, 1]}', r"line 1: .* \(it looks like JSON; name it .json\)"),
    ("type octile\nheight 3\nmap\n...\n", "line 3: expected 'height H' or 'width W', got 'map'"),
    ("type octile\nheight 0\nwidth 3\nmap\n", "line 2: height must be a positive integer, "
                                              "got '0'"),
    ("type octile\nheight -2\nwidth 3\nmap\n", "line 2: height must be a positive integer"),
    ("type octile\nheight 3\nwidth 2.5\nmap\n", "line 3: width must be a positive integer, "
                                                "got '2.5'"),
    ("type octile\nheight 3\nwidth x\nmap\n", "line 3: width must be a positive integer"),
    ("type octile\nwidth 3\nwidth 3\nmap\n", "line 3: width given twice"),
    ("type octile\nheight 1\nwidth 2\nrows\ner\n", "line 4: expected 'map'"),
    ("type octile\nheight 1\nwidth 2\n", "line 4: expected 'map'"),
])
def test_bad_header(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        load_floor(_write(tmp_path, "bad.map", text))


def test_width_before_height_is_accepted(tmp_path: Path) -> None:
    text = "type octile\nwidth 3\nheight 2\nmap\ne.r\n...\n"
    assert load_floor(_write(tmp_path, "wh.map", text)).bounds == (0.0, 0.0, 3.0, 2.0)


@pytest.mark.parametrize(("rows", "height", "match"), [
    (["e..", "...r", "..r"], None, r"line 6 \(grid row 1\) has 4 characters, expected width 3"),
    (["e.r", "..."], 3, "too few rows: the grid has 2 rows after 'map' .* expected height 3"),
    (["e.r", "...", "..."], 2, "too many rows: the grid has 3 rows .* expected height 2"),
    (["e.r", ".x."], None, "line 6, column 2: unknown character 'x'"),
    (["e.r", ". ."], None, "line 6, column 2: unknown character ' '"),
    (["...", ".r."], None, r"no pickup endpoints \(letter 'e'\)"),
    (["e..", "..."], None, r"no stations \(letter 'r'\)"),
])
def test_bad_grid(tmp_path: Path, rows: list[str], height: int | None, match: str) -> None:
    text = _map_text(rows, height=height, width=3)
    with pytest.raises(ValueError, match=match):
        load_floor(_write(tmp_path, "bad.map", text))


def test_pickups_walled_in_are_named(tmp_path: Path) -> None:
    rows = ["r.....", "...@@@", "...@e@", "e..@@@"]
    with pytest.raises(ValueError, match=r"1 of 3 floor points cannot be reached .*"
                                         r"pickups\[0\] at \(4.5, 1.5\)") as err:
        load_floor(_write(tmp_path, "walled.map", _map_text(rows)))
    assert "pickups[1]" not in str(err.value) and "stations" not in str(err.value)


def test_diagonal_gap_does_not_connect(tmp_path: Path) -> None:
    # Two free cells that share only a corner: an AGV cannot squeeze between them.
    rows = ["r@", "@e"]
    with pytest.raises(ValueError, match="cannot be reached"):
        load_floor(_write(tmp_path, "diag.map", _map_text(rows)), cell_size=0.5)


# ---------------------------------------------------------------------- the rectangle merge
def test_solid_block_is_one_rectangle() -> None:
    blocked = np.zeros((6, 7), dtype=bool)
    blocked[1:5, 2:6] = True
    np.testing.assert_allclose(grid_rectangles(blocked, 0.5), [[1.0, 0.5, 3.0, 2.5]])


def test_l_shape_is_two_rectangles() -> None:
    blocked = np.array([[1, 0], [1, 0], [1, 1]], dtype=bool)
    rects = grid_rectangles(blocked)
    assert len(rects) == 2
    np.testing.assert_allclose(rects, [[0.0, 1.0, 1.0, 3.0], [0.0, 0.0, 2.0, 1.0]])


def test_empty_and_full_grids() -> None:
    assert grid_rectangles(np.zeros((3, 4), dtype=bool)).shape == (0, 4)
    np.testing.assert_allclose(grid_rectangles(np.ones((3, 4), dtype=bool)), [[0, 0, 4, 3]])


@pytest.mark.parametrize("density", [0.2, 0.5, 0.8])
def test_rectangles_cover_the_blocked_cells_exactly(density: float) -> None:
    gen = np.random.default_rng(13)
    for _ in range(60):
        H, W = gen.integers(1, 12, size=2)
        blocked = gen.random((H, W)) < density
        cell = float(gen.choice([0.3, 1.0, 1.7]))
        rects = grid_rectangles(blocked, cell)
        covered = _covered(rects, blocked.shape, cell)
        assert (covered == blocked).all()  # union exact, no cell covered twice
        area = np.sum((rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1]))
        assert area == pytest.approx(blocked.sum() * cell**2)  # disjoint, on the cell lines
        assert len(rects) <= blocked.sum()
        # No more rectangles than maximal row runs: merging never splits a run.
        runs = np.sum(np.diff(np.pad(blocked.astype(int), ((0, 0), (1, 0))), axis=1) == 1)
        assert len(rects) <= runs


def test_grid_rectangles_bad_input() -> None:
    with pytest.raises(ValueError, match=r"blocked must be an \(H, W\) bool array"):
        grid_rectangles(np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"blocked must be an \(H, W\) bool array"):
        grid_rectangles(np.zeros(3, dtype=bool))
    with pytest.raises(ValueError, match="cell_size must be a positive finite number"):
        grid_rectangles(np.zeros((3, 3), dtype=bool), 0.0)


# ---------------------------------------------------------------------- JSON floor plans
def test_load_json_plan(tmp_path: Path) -> None:
    world = load_floor(_write(tmp_path, "floor.json", json.dumps(_plan())))
    assert world.bounds == (0.0, 0.0, 4.0, 3.0)
    np.testing.assert_array_equal(world.obstacles, [[1.0, 1.0, 3.0, 1.6]])
    np.testing.assert_array_equal(world.pickups, [[1.5, 0.8], [2.5, 1.8]])
    np.testing.assert_array_equal(world.stations, [[0.3, 2.7]])
    np.testing.assert_array_equal(world.depot, [[0.0, 0.0, 1.0, 0.6]])


def test_json_shelves_and_depot_are_optional_and_radius_is_read(tmp_path: Path) -> None:
    plan = _plan(shelves=None, depot=None, agent_radius=0.1, capture_radius=0.05)
    world = load_floor(_write(tmp_path, "open.json", json.dumps(plan)))
    assert world.obstacles.shape == (0, 4) and world.depot.shape == (0, 4)
    assert world.agent_radius == 0.1 and world.capture_radius == 0.05
    assert load_floor(tmp_path / "open.json", agent_radius=0.1).agent_radius == 0.1
    with pytest.raises(ValueError, match="agent_radius=0.2 was given, but the plan says "
                                         "agent_radius 0.1"):
        load_floor(tmp_path / "open.json", agent_radius=0.2)


def test_format_is_chosen_by_content_for_other_names(tmp_path: Path) -> None:
    as_map = load_floor(_write(tmp_path, "floor.txt", _map_text(KIVA)), cell_size=0.5)
    assert len(as_map.pickups) == 16
    as_json = load_floor(_write(tmp_path, "plan", json.dumps(_plan())))
    assert len(as_json.pickups) == 2
    with pytest.raises(ValueError, match="floor.csv'.*cannot tell its format"):
        load_floor(_write(tmp_path, "floor.csv", "x,y\n1,2\n"))


def test_a_grid_map_named_json_gets_a_hint(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"not valid JSON: .*\(it looks like a grid map; name "
                                         r"it .map\)"):
        load_floor(_write(tmp_path, "kiva.json", _map_text(KIVA)))


def test_cell_size_with_a_json_plan_is_an_error(tmp_path: Path) -> None:
    path = _write(tmp_path, "floor.json", json.dumps(_plan()))
    with pytest.raises(ValueError, match="cell_size applies to grid maps"):
        load_floor(path, cell_size=0.5)


@pytest.mark.parametrize(("text", "match"), [
    ("[1, 2]", "a floor plan is a JSON object .* got a list"),
    ('{"bounds": [0, 0, 4, 3],', "not valid JSON: .* line 1, column"),
    (json.dumps(_plan(pickups=None)), r"missing key\(s\) \['pickups'\]"),
    (json.dumps(_plan(stations=None)), r"missing key\(s\) \['stations'\]"),
    (json.dumps(_plan(pickup=[[1, 1]])), r"unknown key\(s\) \['pickup'\]"),
    (json.dumps(_plan(bounds=[0, 0, 4])), r"'bounds' must be \[xmin, ymin, xmax, ymax\]"),
    (json.dumps(_plan(bounds=[0, 0, "4", 3])), r"bounds\[2\] must be a number, got '4'"),
    (json.dumps(_plan(bounds=[0, 0, 1, 1], pickups=[[0.5, 0.5]], stations=[[0.5, 0.5]],
                      shelves=[], depot=[], agent_radius=0.6)),
     "agent_radius 0.6 is too large for bounds"),
    (json.dumps(_plan(shelves=[[1, 1, 3]])), r"shelves\[0\] must be \[xmin, ymin, xmax, ymax\]"),
    (json.dumps(_plan(shelves={"a": 1})), "'shelves' must be a list"),
    (json.dumps(_plan(shelves=[[3, 1, 1, 1.6]])), r"shelves\[0\] = .* has xmax <= xmin"),
    (json.dumps(_plan(shelves=[[1, 2, 3, 1.6]])), r"shelves\[0\] = .* has ymax <= ymin"),
    (json.dumps(_plan(depot=[[1, 0, 0.5, 1]])), r"depot\[0\] = .* has xmax <= xmin"),
    (json.dumps(_plan(pickups=[[1.5, float("nan")]])), r"pickups\[0\]\[1\] must be a finite"),
    (json.dumps(_plan(pickups=[[1.5, True]])), r"pickups\[0\]\[1\] must be a number"),
    (json.dumps(_plan(pickups=[[1.5, 0.8, 0]])), r"pickups\[0\] must be \[x, y\]"),
    (json.dumps(_plan(pickups=[[1.5, 0.8], [2.0, 1.3]])), r"pickups\[1\] at \(2, 1.3\): inside "
                                                          "a shelf"),
    (json.dumps(_plan(stations=[[4.5, 1.0]])), r"stations\[0\] at \(4.5, 1\): outside the world"),
    (json.dumps(_plan(pickups=[])), "'pickups' is empty; a lifelong floor needs"),
    (json.dumps(_plan(stations=[])), "'stations' is empty"),
    (json.dumps(_plan(agent_radius="big")), "agent_radius must be a number"),
])
def test_bad_json(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ValueError, match=match) as err:
        load_floor(_write(tmp_path, "bad.json", text))
    assert "bad.json" in str(err.value)  # every message names the file


def test_json_station_cut_off_by_shelves_is_named(tmp_path: Path) -> None:
    # A shelf wall across the floor from bottom to top, station on the other side.
    plan = _plan(shelves=[[2.0, 0.0, 2.2, 3.0]], pickups=[[1.0, 1.0], [3.0, 1.0]],
                 stations=[[0.5, 2.5]], depot=[[0.0, 0.0, 1.0, 0.6]])
    with pytest.raises(ValueError, match=r"1 of 4 floor points .* pickups\[1\] at \(3, 1\)"):
        load_floor(_write(tmp_path, "cut.json", json.dumps(plan)))


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nowhere.map"):
        load_floor(tmp_path / "nowhere.map")
    with pytest.raises(ValueError, match="is a directory"):
        load_floor(tmp_path)
    (tmp_path / "bin.map").write_bytes(b"\xff\xfe\x00type")
    with pytest.raises(ValueError, match="not a UTF-8 text file"):
        load_floor(tmp_path / "bin.map")


# ---------------------------------------------------------------------- saving
@pytest.mark.parametrize("source", ["warehouse", "map", "json"])
def test_save_and_load_round_trip(tmp_path: Path, source: str) -> None:
    if source == "warehouse":
        world = warehouse_floor(20)
    elif source == "map":
        world = load_floor(_write(tmp_path, "kiva.map", _map_text(KIVA)), cell_size=0.7)
    else:
        world = load_floor(_write(tmp_path, "in.json", json.dumps(_plan(capture_radius=0.07))))
    out = save_floor_json(world, tmp_path / "sub" / "out.json")
    assert out == tmp_path / "sub" / "out.json"
    back = load_floor(out)
    assert back.bounds == world.bounds
    for name in ("obstacles", "pickups", "stations", "depot"):
        np.testing.assert_array_equal(getattr(back, name), getattr(world, name))
    assert (back.agent_radius, back.capture_radius) == (world.agent_radius, world.capture_radius)
    assert [p.name for p in out.parent.iterdir()] == ["out.json"]  # no temporary left behind


def test_save_refuses_what_load_would_refuse(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="a floor plan needs both"):
        save_floor_json(sim.World(), tmp_path / "x.json")
    with pytest.raises(ValueError, match="world must be a sim.World"):
        save_floor_json({"bounds": [0, 0, 1, 1]}, tmp_path / "x.json")  # type: ignore[arg-type]
    assert not (tmp_path / "x.json").exists()


# ---------------------------------------------------------------------- reachability
def test_raster_matches_world_is_free() -> None:
    world = sim.World(bounds=(0.0, 0.0, 3.0, 2.0),
                      obstacles=np.array([[0.5, 0.5, 1.3, 0.9], [1.7, 0.2, 2.1, 1.8]]))
    free, x, y = _free_raster(world, 0.05)
    centres = np.stack(np.meshgrid(x, y), axis=-1)  # (H, W, 2)
    clearance = world.agent_radius - 0.5 * math.hypot(x[1] - x[0], y[1] - y[0]) - 1e-9
    np.testing.assert_array_equal(free, world.is_free(centres, clearance=clearance))


def test_gap_narrower_than_an_agv_blocks_and_one_exactly_as_wide_passes() -> None:
    r = 0.15

    def floor(gap: float) -> sim.World:  # a wall across the floor with one gap in it
        return sim.World(bounds=(0.0, 0.0, 3.0, 2.0), agent_radius=r,
                         obstacles=np.array([[1.4, 0.0, 1.6, 1.0 - gap / 2],
                                             [1.4, 1.0 + gap / 2, 1.6, 2.0]]),
                         pickups=[[0.5, 1.0]], stations=[[2.5, 1.0]])

    check_reachable(floor(2 * r))
    with pytest.raises(ValueError, match=r"stations\[0\] at \(2.5, 1\)"):
        check_reachable(floor(1.5 * r))
    with pytest.raises(ValueError, match="cannot be reached"):
        check_reachable(floor(1.5 * r), resolution=r / 8)


def test_check_reachable_bad_input_and_trivial_worlds() -> None:
    check_reachable(sim.World())  # nothing to reach
    with pytest.raises(ValueError, match="resolution must be at most half the AGV radius"):
        check_reachable(warehouse_floor(5), resolution=0.1)
    with pytest.raises(ValueError, match="resolution must be a positive finite number"):
        check_reachable(warehouse_floor(5), resolution=-1.0)
    with pytest.raises(ValueError, match="world must be a sim.World"):
        check_reachable("warehouse-20")  # type: ignore[arg-type]


def test_unreachable_depot_is_named() -> None:
    world = sim.World(bounds=(0.0, 0.0, 4.0, 2.0), obstacles=np.array([[2.8, 0.0, 3.0, 2.0]]),
                      pickups=[[0.5, 0.5], [1.5, 1.5]], stations=[[0.5, 1.5]],
                      depot=[[3.0, 0.0, 4.0, 2.0]])
    with pytest.raises(ValueError, match=r"1 of 4 floor points .* depot\[0\] at \(3.5, 1\)"):
        check_reachable(world)


# ---------------------------------------------------------------------- the warehouses
def _rect_gap(a: np.ndarray, b: np.ndarray) -> float:
    dx = max(a[0] - b[2], b[0] - a[2], 0.0)
    dy = max(a[1] - b[3], b[1] - a[3], 0.0)
    return math.hypot(dx, dy)


@pytest.mark.parametrize("n", [1, 7, 20, 50, 100])
def test_warehouse_floor(n: int) -> None:
    world = warehouse_floor(n)
    r = world.agent_radius
    shelves, pickups, stations = world.obstacles, world.pickups, world.stations
    width, height = world.size
    assert world.bounds[:2] == (0.0, 0.0) and world.is_floor
    # Aisles of 0.8 (two AGVs wide and more), between shelves and between shelves and walls;
    # each shelf block is one rectangle, so no two rectangles touch.
    assert 0.8 >= 4 * r
    for i in range(len(shelves)):
        for j in range(i):
            assert _rect_gap(shelves[i], shelves[j]) >= 0.8 - 1e-9
        x0, y0, x1, y1 = shelves[i]
        assert min(x0, y0, width - x1, height - y1) >= 0.8 - 1e-9
    # Pickups: at least 2N, on a long face, r + 0.05 out, one AGV apart with room.
    assert len(pickups) >= 2 * n
    dy = np.minimum(np.abs(pickups[:, None, 1] - shelves[None, :, 1]),
                    np.abs(pickups[:, None, 1] - shelves[None, :, 3]))
    on_face = (np.abs(dy - (r + 0.05)) < 1e-9) \
        & (pickups[:, None, 0] > shelves[None, :, 0]) & (pickups[:, None, 0] < shelves[None, :, 2])
    assert on_face.any(axis=1).all()
    gaps = np.linalg.norm(pickups[:, None] - pickups[None], axis=-1) + 9 * np.eye(len(pickups))
    assert gaps.min() >= 2 * r + 0.1 - 1e-9
    # Stations: enough, 0.8 apart, in the zone left of every shelf.
    assert len(stations) >= max(4, n // 5)
    sgaps = np.linalg.norm(stations[:, None] - stations[None], axis=-1) + 9 * np.eye(len(stations))
    assert sgaps.min() >= 0.8 - 1e-9
    assert stations[:, 0].max() < shelves[:, 0].min() - 0.8
    # The depot: one strip along the bottom, 4 N (2r)^2 of area, and N AGVs one diameter apart.
    assert world.depot.shape == (1, 4) and world.depot[0, 1] == 0.0
    x0, y0, x1, y1 = world.depot[0]
    assert (x1 - x0) * (y1 - y0) >= 4 * n * (2 * r) ** 2 - 1e-9
    gx = np.arange(x0 + r, x1 - r + 1e-9, 2 * r)
    gy = np.arange(y0 + r, y1 - r + 1e-9, 2 * r)
    slots = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    assert len(slots) >= 2 * n and world.in_depot(slots).all() and world.is_free(slots).all()
    assert not world.in_depot(pickups).any() and not world.in_depot(stations).any()
    # Shape: width / height about 1.25.
    assert 1.15 <= width / height <= 1.4
    check_reachable(world)


@pytest.mark.parametrize(("n", "size"), [(20, (7.2, 6.2)), (50, (11.2, 9.6)),
                                         (100, (15.6, 11.8))])
def test_warehouse_scenario_floors_keep_their_size(n: int, size: tuple[float, float]) -> None:
    # Regression: the floors of warehouse-20/50/100 are part of the benchmark; a change of
    # layout changes every published lifelong number.
    world = warehouse_floor(n)
    assert world.size == pytest.approx(size)
    assert world.size[0] * world.size[1] <= 2.3 * n


def test_warehouse_floor_is_deterministic() -> None:
    a, b = warehouse_floor(50), warehouse_floor(50)
    for name in ("obstacles", "pickups", "stations", "depot"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_warehouse_floor_scales_for_larger_agvs() -> None:
    world = warehouse_floor(20, agent_radius=0.3)
    r = world.agent_radius
    assert r == 0.3
    shelves = world.obstacles
    gaps = [_rect_gap(shelves[i], shelves[j]) for i in range(len(shelves)) for j in range(i)]
    assert min(gaps, default=np.inf) >= 4 * r
    assert len(world.pickups) >= 40 and world.is_free(world.pickups).all()
    # A smaller AGV keeps the shelves and aisles; only the depot it needs shrinks.
    small, standard = warehouse_floor(20, agent_radius=0.1), warehouse_floor(20)
    size = lambda w: np.stack([w.obstacles[:, 2] - w.obstacles[:, 0],  # noqa: E731
                               w.obstacles[:, 3] - w.obstacles[:, 1]], 1)
    np.testing.assert_allclose(size(small), size(standard))
    assert small.depot[0, 3] < standard.depot[0, 3]


@pytest.mark.parametrize("bad", [0, -3, 2.0, True, "20", None])
def test_warehouse_floor_bad_num_agents(bad: object) -> None:
    with pytest.raises(ValueError, match="num_agents must be an int >= 1"):
        warehouse_floor(bad)  # type: ignore[arg-type]


def test_warehouse_floor_bad_radius() -> None:
    with pytest.raises(ValueError, match="agent_radius must be a positive finite number"):
        warehouse_floor(20, agent_radius=0.0)


def test_unreachable_points_names_the_cut_off_ones() -> None:
    from sim.floors import unreachable_points

    world = warehouse_floor(20)
    x0, y0, x1, y1 = world.obstacles[0]
    inside_block = [(x0 + x1) / 2, (y0 + y1) / 2]  # on a shelf: no free cell there
    points = np.array([world.pickups[0], world.stations[0], inside_block])
    assert unreachable_points(world, points).tolist() == [2]
    assert unreachable_points(world, np.zeros((0, 2))).tolist() == []
    # A floor without points of its own: the main area is the one most points lie in.
    assert unreachable_points(sim.World(), np.array([[0.0, 0.0], [0.5, 0.5]])).tolist() == []
