"""The map prior's network (a small U-Net) and :class:`MapPrior`, the object planners are handed.

The network is fully convolutional, so one prior reads maps of any size. Its input has four
channels per cell: seen free, seen wall, unseen (one-hot), and inside the map (the map is padded
to a multiple of the network's downsampling with cells coded as seen walls outside it). Its
output is one logit per cell: the log-odds that the cell is a wall. Where the team has seen a
cell the prediction is the cell itself (:meth:`MapPrior.wall_probability`).

A prior is saved as a zip of ``prior.pt`` (the weights, read back with
``torch.load(weights_only=True)``: no pickled objects) and ``prior.json`` (the network's
shape), the ``model.zip`` of a prior run (docs/prior.md).
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from harness.prior.coding import SEEN_FREE, SEEN_WALL, UNSEEN, code_team_map

#: ``prior.json``'s ``kind``: what marks a zip as a map prior.
KIND = "map_prior"
WEIGHTS, META = "prior.pt", "prior.json"
#: Input channels: seen free, seen wall, unseen, inside the map.
IN_CHANNELS = 4


class _Block(nn.Sequential):
    """Two 3x3 convolutions with ReLU, same size."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__(
            nn.Conv2d(cin, cout, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, padding=1),
            nn.ReLU(inplace=True),
        )


class UNet(nn.Module):
    """A U-Net (Ronneberger et al. 2015) with ``channels[i]`` features at level ``i``: each level
    halves the size (max pooling), the way back doubles it and joins the level's features.

    Args:
        channels: Features per level, e.g. ``(16, 32, 64)`` (3 levels: sizes divisible by 4).
    """

    def __init__(self, channels: Sequence[int]) -> None:
        super().__init__()
        channels = [int(c) for c in channels]
        if not channels or min(channels) < 1:
            raise ValueError(f"channels must be positive integers, got {channels!r}")
        self.channels = channels
        self.down = nn.ModuleList()
        cin = IN_CHANNELS
        for c in channels:
            self.down.append(_Block(cin, c))
            cin = c
        self.up = nn.ModuleList(
            _Block(channels[i] + channels[i + 1], channels[i]) for i in range(len(channels) - 1)
        )
        self.head = nn.Conv2d(channels[0], 1, 1)

    @property
    def multiple(self) -> int:
        """What the input's height and width must divide by."""
        return 2 ** (len(self.channels) - 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits ``(N, H, W)`` of inputs ``(N, 4, H, W)`` (sizes divisible by :attr:`multiple`)."""
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        for i in reversed(range(len(self.up))):
            x = F.interpolate(x, scale_factor=2.0, mode="nearest")
            x = self.up[i](torch.cat([skips[i], x], dim=1))
        return self.head(x)[:, 0]


def encode(states: np.ndarray, multiple: int) -> torch.Tensor:
    """The network's input for partial maps ``states`` (``uint8 (N, H, W)`` codes), padded at
    the bottom and right to sizes divisible by ``multiple`` (outside cells: seen walls, not
    inside): ``float32 (N, 4, H', W')``."""
    states = np.asarray(states)
    n, h, w = states.shape
    hp, wp = -(-h // multiple) * multiple, -(-w // multiple) * multiple
    padded = np.full((n, hp, wp), SEEN_WALL, dtype=np.uint8)
    padded[:, :h, :w] = states
    x = np.zeros((n, IN_CHANNELS, hp, wp), dtype=np.float32)
    for channel, code in enumerate((SEEN_FREE, SEEN_WALL, UNSEEN)):
        x[:, channel] = padded == code
    x[:, 3, :h, :w] = 1.0
    return torch.from_numpy(x)


class MapPrior:
    """A trained map prior: :meth:`wall_probability` of a team's map. Hand it to the rollout
    chooser (``eval.rollout.prior``), which calls it as ``prior(seen, free)``.

    Args:
        net: The network (put in evaluation mode, on the CPU).
    """

    def __init__(self, net: UNet) -> None:
        self.net = net.eval()

    @torch.no_grad()
    def logits(self, states: np.ndarray) -> np.ndarray:
        """Logits ``float32 (N, H, W)`` for partial maps ``states`` (``uint8 (N, H, W)``)."""
        states = np.asarray(states)
        h, w = states.shape[-2:]
        return self.net(encode(states, self.net.multiple))[:, :h, :w].numpy()

    def wall_probability(self, states: np.ndarray) -> np.ndarray:
        """The probability that each cell is a wall, ``float64 (N, H, W)``: the seen cells as
        they are (0 or 1), the unseen ones as the network predicts."""
        states = np.asarray(states)
        p = 1.0 / (1.0 + np.exp(-self.logits(states).astype(np.float64)))
        p[states == SEEN_FREE] = 0.0
        p[states == SEEN_WALL] = 1.0
        return p

    def __call__(self, seen: np.ndarray, free: np.ndarray) -> np.ndarray:
        """The chooser's interface: ``bool (H, W)`` seen cells and free cells (read only where
        seen) to wall probabilities ``float64 (H, W)``."""
        states = code_team_map(seen, ~np.asarray(free, dtype=bool))
        return self.wall_probability(states[None])[0]

    def to_bytes(self) -> bytes:
        """The prior as a zip (``prior.pt`` and ``prior.json``)."""
        return archive({"state_dict": self.net.state_dict()}, {"channels": self.net.channels})

    def save(self, path: Path) -> None:
        """Write the zip to ``path`` (whole or not at all: a temporary file, then a rename)."""
        from harness.results.rundir import atomic_write

        data = self.to_bytes()
        atomic_write(Path(path), lambda tmp: tmp.write_bytes(data))

    @classmethod
    def load(cls, path: Path | str) -> MapPrior:
        """A prior saved by :meth:`save` (or a prior run's checkpoint ``model.zip``).

        Raises:
            ValueError: one line naming the file, when it is no map prior.
        """
        weights, meta = read_archive(Path(path))
        net = UNet(meta["channels"])
        try:
            net.load_state_dict(weights["state_dict"])
        except (KeyError, RuntimeError) as exc:
            raise ValueError(
                f"{path}: not the weights of its prior.json's network ({exc})"
            ) from None
        return cls(net)


def archive(weights: dict[str, Any], meta: dict[str, Any]) -> bytes:
    """A zip of ``weights`` (tensors, numbers, lists and dicts of them) and ``meta`` (JSON)."""
    tensors = io.BytesIO()
    torch.save(weights, tensors)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(WEIGHTS, tensors.getvalue())
        zf.writestr(META, json.dumps({"kind": KIND, **meta}))
    return out.getvalue()


def read_archive(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """What :func:`archive` wrote, read back without unpickling any object.

    Raises:
        ValueError: one line naming the file.
    """
    try:
        with zipfile.ZipFile(path) as zf:
            meta = json.loads(zf.read(META))
            raw = zf.read(WEIGHTS)
    except (OSError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a map prior ({exc})") from None
    if not isinstance(meta, dict) or meta.get("kind") != KIND:
        raise ValueError(f"{path}: not a map prior (its {META} does not say {KIND!r})")
    try:
        weights = torch.load(io.BytesIO(raw), weights_only=True, map_location="cpu")
    except Exception as exc:  # torch raises many kinds on a damaged file
        raise ValueError(f"{path}: unreadable {WEIGHTS} ({type(exc).__name__}: {exc})") from None
    return weights, meta


def load_prior(path: str | Path) -> MapPrior:
    """The prior of a prior run's folder (its ``model.zip``: the weights that scored best on the
    validation episodes) or of a prior zip.

    Raises:
        ValueError: one line naming the path.
    """
    from harness.results.rundir import RunDir

    path = Path(path)
    if path.is_dir():
        run = RunDir(path)
        if not run.is_run:
            raise ValueError(f"{path}: not a prior run folder (no config.yaml)")
        path = run.model
        if not path.is_file():
            raise ValueError(f"{path.parent}: no model.zip yet (the prior's training unfinished)")
    elif not path.is_file():
        raise ValueError(f"{path}: no such prior run folder or prior file")
    return MapPrior.load(path)
