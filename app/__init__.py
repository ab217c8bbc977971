"""drop-rl service: the HTTP API in front of drop_engine (datasets, jobs, policies)."""
