"""Map priors: a network trained by the harness that predicts the unseen part of the team's map.

A map prior maps the team's map (each cell seen free, seen wall or unseen) to the probability
that each unseen cell is a wall. On maps with structure (floor plans, mazes, caves) what the
team has seen predicts what it has not; on the thesis's random maps every wall is independent,
and the best a prior can do is the wall share of the seen cells (docs/prior.md).

* :mod:`harness.prior.data`: partial maps recorded along episodes of a written planner;
* :mod:`harness.prior.model`: the fully convolutional network and :class:`MapPrior`, the object
  handed to the rollout chooser (the env and the planners never import torch);
* :mod:`harness.prior.score`: the log-loss on unseen cells against the seen wall share;
* :mod:`harness.training.prior`: ``harness run`` of a config with a ``prior:`` section.
"""
