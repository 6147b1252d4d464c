"""``agv render --lifelong SCENARIO``: a GIF of a lifelong run of the nearest-task controller
and, with ``--plot``, its throughput and waits over time; every bad flag is one line on standard
error with exit status 2."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from PIL import Image

from allocator.cli import main
from sim.render import LIFELONG_COLORS


def run_main(capsys: pytest.CaptureFixture[str], argv: list[str]) -> tuple[int, str, str]:
    """``main(argv)`` in this process: ``(exit status, stdout, stderr)``."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err


def user_error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Exit status 2, no traceback; the last line of standard error."""
    code, out, err = run_main(capsys, argv)
    assert code == 2, (code, out, err)
    assert "Traceback" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("agv render: error: "), last
    return last


def test_lifelong_gif_and_plot_are_written(capsys, tmp_path) -> None:
    gif, png = tmp_path / "out" / "run.gif", tmp_path / "plots" / "run.png"
    code, out, err = run_main(capsys, [
        "render", "--lifelong", "warehouse-20", "--steps", "6", "--seed", "2",
        "--faults", "0.2:3", "--out", str(gif), "--plot", str(png)])
    assert code == 0, err
    assert f"wrote {gif}" in out and f"wrote {png}" in out
    assert "throughput" in out and "bound" in out
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.n_frames == 7
        # At a rate of 0.2 per AGV-step some of the 20 AGVs are broken by the last frame.
        im.seek(im.n_frames - 1)
        last = np.asarray(im.convert("RGB")).astype(int)
        im.seek(0)
        first = np.asarray(im.convert("RGB")).astype(int)
    red = np.array([int(LIFELONG_COLORS["broken"][k:k + 2], 16) for k in (1, 3, 5)])
    reds = [int((np.abs(f - red) <= 12).all(-1).sum()) for f in (first, last)]
    assert reds[1] > reds[0] + 30
    with Image.open(png) as im:
        assert im.format == "PNG"
    assert sorted(p.name for p in gif.parent.iterdir()) == ["run.gif"]


def test_lifelong_default_file_name_and_the_threads_come_back(capsys, tmp_path,
                                                              monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        code, out, err = run_main(capsys, ["render", "--lifelong", "warehouse-20", "--steps",
                                           "2"])
        assert torch.get_num_threads() == 2  # the CLI ran on one thread, then restored them
    finally:
        torch.set_num_threads(threads)
    assert code == 0, err
    with Image.open(tmp_path / "lifelong_warehouse-20.gif") as im:
        assert im.n_frames == 3
    assert out.strip() == "wrote lifelong_warehouse-20.gif"


@pytest.mark.parametrize(("argv", "fragments"), [
    (["--lifelong", "3v3"], ("argument --lifelong", "episodic")),
    (["--lifelong", "nowhere-7"], ("argument --lifelong",)),
    (["--lifelong", "warehouse-20", "--steps", "0"], ("argument --steps", "'0'")),
    (["--lifelong", "warehouse-20", "--steps", "1.5"], ("argument --steps",)),
    (["--lifelong", "warehouse-20", "--faults", "0.1"], ("argument --faults", "RATE:REPAIR")),
    (["--lifelong", "warehouse-20", "--faults", "2:5"], ("argument --faults", "(0, 1]")),
    (["--lifelong", "warehouse-20", "--faults", "0:5"], ("argument --faults",)),
    (["--lifelong", "warehouse-20", "--faults", "0.1:0"], ("argument --faults",
                                                          "repair_steps")),
    (["--lifelong", "warehouse-20", "--faults", "x:5"], ("argument --faults", "RATE 'x'")),
    (["--lifelong", "warehouse-20", "--faults", "0.1:y"], ("argument --faults",
                                                          "REPAIR 'y'")),
    (["--lifelong", "warehouse-20", "--seed", "-1"], ("argument --seed",)),
    (["--lifelong", "warehouse-20", "--gif"], ("not allowed with argument",)),
    (["--lifelong", "warehouse-20", "--field"], ("not allowed with argument",)),
    (["--lifelong", "warehouse-20", "--scenario", "3v3"], ("--lifelong", "--scenario")),
    (["--lifelong", "warehouse-20", "--agent", "1"], ("--agent", "--field")),
    (["--lifelong", "warehouse-20", "--out", "run.png"], ("--out", ".gif")),
    (["--lifelong", "warehouse-20", "--plot", "plot.txt"], ("--plot", ".png")),
    (["--lifelong", "warehouse-20", "--plot", "same.gif", "--out", "same.gif"],
     ("--plot", "another name")),
    (["--steps", "5"], ("--steps", "--lifelong")),
    (["--faults", "0.1:5"], ("--faults", "--lifelong")),
    (["--gif", "--plot", "p.png"], ("--plot", "--lifelong")),
    (["--scenario", "warehouse-20"], ("lifelong scenario", "--lifelong warehouse-20")),
    (["--gif", "--scenario", "warehouse-50"], ("--lifelong warehouse-50",)),
    (["--field", "--scenario", "warehouse-20"], ("--lifelong warehouse-20",)),
])
def test_bad_lifelong_flags_are_one_line_and_exit_2(capsys, tmp_path, monkeypatch, argv,
                                                    fragments) -> None:
    monkeypatch.chdir(tmp_path)
    line = user_error(capsys, ["render", *argv])
    for fragment in fragments:
        assert fragment in line, (fragment, line)
    assert not list(tmp_path.iterdir())  # nothing written


def test_render_without_lifelong_keeps_its_default_scenario(capsys, tmp_path,
                                                            monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    code, _, err = run_main(capsys, ["render"])
    assert code == 0, err
    assert (tmp_path / "scene_3v3.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_help_lists_the_lifelong_flags(capsys) -> None:
    code, out, _ = run_main(capsys, ["render", "--help"])
    assert code == 0
    for flag in ("--lifelong SCENARIO", "--steps", "--faults RATE:REPAIR", "--plot PATH"):
        assert flag in out, flag


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
