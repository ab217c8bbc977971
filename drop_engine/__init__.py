"""drop_engine: DROP, MOPO and MBPO offline policy optimisation, with no web or database code.

Entry points: `config.build_config` for a validated `TrainConfig`, `trainer.train` to run it (resumable, with a
`callbacks.Callback`), `export` for the trained policy, `collect` for D4RL-style datasets.
"""
