"""Configuration: the typed schema (:mod:`~harness.config.schema`), YAML loading and ``--set``
overrides (:mod:`~harness.config.loading`), map sources (:mod:`~harness.config.maps`) and the
migration of old files (:mod:`~harness.config.migrate`).

Imports nothing from training, evaluation or the CLI, and builds no environment, but for a
PettingZoo env of one's own (:mod:`~harness.config.pettingzoo`), which validating its config
imports and builds once to check its spaces.
"""

from harness.config.loading import config_from_dict, load_config
from harness.config.schema import ConfigError, EnvConfig, ExperimentConfig

__all__ = ["ConfigError", "EnvConfig", "ExperimentConfig", "config_from_dict", "load_config"]
