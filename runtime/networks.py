"""Which network a scene renders with.

A scene has a coarse network and, when it was trained with nerf-pytorch's hierarchy, a fine one. The
render network is the fine one where there is one: models, bundles and ordinary renders all follow this
one rule (a bundle tile that names no network means it).
"""

from __future__ import annotations

from typing import Iterable

NETWORKS = ("coarse", "fine")


def render_network(names: Iterable[str]) -> str:
    """The render network of a scene whose networks are `names`: the fine one where there is one."""
    return "fine" if "fine" in names else "coarse"


def network_names(has_fine: bool) -> tuple[str, ...]:
    """The networks a scene has, in NETWORKS order."""
    return NETWORKS if has_fine else NETWORKS[:1]
