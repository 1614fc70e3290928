# Every target bootstraps .venv from the lock file, so a fresh clone needs only python3 >= 3.11.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.kincal-installed

.PHONY: demo test lint docs bench serve lock clean

$(STAMP): requirements.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade "pip>=24"
	$(BIN)/pip install --quiet -r requirements.lock
	$(BIN)/pip install --quiet --no-deps -e .
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/kincal demo

# The suite starts ~100 Python processes (servers, their children, CLI runs): it lets them cache
# bytecode in the clone's __pycache__ (git-ignored) even where the environment turns that off.
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy solver schemas service benchmarks
	$(BIN)/lint-imports
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet --site-dir build/site
	PYTHONDONTWRITEBYTECODE= $(BIN)/pytest -q -n 2 --durations=15

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy solver schemas service benchmarks
	$(BIN)/lint-imports

# The documentation site (docs/, mkdocs.yml) on http://127.0.0.1:8001, rebuilt on every edit.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs serve --dev-addr 127.0.0.1:8001

bench: $(STAMP)
	$(BIN)/python -m benchmarks.evaluate_real

serve: $(STAMP)
	$(BIN)/kincal serve

# Re-pin dependencies after editing pyproject.toml (needs uv: pip install uv).
lock:
	uv pip compile pyproject.toml --extra dev --python-version 3.11 -o requirements.lock

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .hypothesis build site *.egg-info
