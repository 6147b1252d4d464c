"""The paper's reported numbers (Tables I and II), for side-by-side comparison."""

from __future__ import annotations

__all__ = ["PAPER_TABLES"]

# scenario -> method -> (task response rate, average reward, average time)
PAPER_TABLES: dict[str, dict[str, tuple[float, float, float]]] = {
    "3v3": {
        "maddpg-minidist": (0.8864, -101.1, 14.3),
        "maddpg-greedy": (0.8867, -116.61, 11.8),
        "maddpg-ipf": (0.9500, -85.8, 11.1),
        "bicnet-minidist": (0.9303, -71.5, 10.4),
        "bicnet-greedy": (0.7356, -143.8, 10.2),
        "bicnet-ipf": (0.9758, -65.8, 9.7),
    },
    "6v6": {
        "maddpg-minidist": (0.6922, -438.5, 17.7),
        "maddpg-greedy": (0.4606, -675.0, 17.1),
        "maddpg-ipf": (0.8022, -371.5, 16.2),
        "bicnet-minidist": (0.8044, -249.8, 16.0),
        "bicnet-greedy": (0.4456, -664.5, 17.5),
        "bicnet-ipf": (0.9161, -241.1, 15.6),
    },
}
