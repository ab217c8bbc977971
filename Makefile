# The README's two commands: `make run` and `make test`. Both create .venv on first use; CI also runs `make lint`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install run test lint bench-data bench-speed bench-table bench-penalty bench-load clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[service,dev]'
	touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(BIN)/drop serve

test: $(STAMP)
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check .

# D4RL-style benchmark datasets (random, medium, medium-replay, medium-expert) made by `drop collect` (one torch
# thread each), BENCH_JOBS envs at a time, into a cache outside the repo (times: README). Rerunning resumes.
BENCH_ENVS ?= hopper walker2d halfcheetah
BENCH_JOBS ?= 2
bench-data: $(STAMP)
	out="$${DROP_BENCH_DATA:-$$HOME/.cache/drop-rl/bench-data}"; \
	printf '%s\n' $(BENCH_ENVS) | xargs -P $(BENCH_JOBS) -I {} $(BIN)/drop collect --env {} --out "$$out" \
		--no-progress --kinds random,medium,medium-replay,medium-expert

# Benchmarks (on demand, never in CI); results land in bench/results/.
bench-speed: $(STAMP)
	$(BIN)/python bench/engine_speed.py

bench-table: $(STAMP)
	$(BIN)/python bench/paper_table.py --envs $(BENCH_ENVS)

# Needs a finished DROP run: make bench-penalty RUN=runs/hopper-drop DATASET=.../hopper-medium.hdf5
bench-penalty: $(STAMP)
	$(BIN)/python bench/penalty_vs_error.py --run $(RUN) --dataset $(DATASET)

# Needs PostgreSQL on 127.0.0.1:5432 (user postgres) and Redis on 127.0.0.1:6379, as the service tests do.
bench-load: $(STAMP)
	$(BIN)/python bench/service_load.py

clean:
	rm -rf $(VENV) .pytest_cache
