"""PettingZoo envs of the tests' own (``env: {pettingzoo: {make: "tests.envs.<module>:..."}}``)."""
