# The two commands of README.md: `make demo` and `make test`. Each sets up its own
# virtual environment (idempotent: it reinstalls only when pyproject.toml changes).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
EXTRAS ?= onboard,ground,sim,dev
comma := ,
STAMP := $(VENV)/.installed-$(subst $(comma),-,$(EXTRAS))
FLIGHT ?= replay_data/demo-flight
OUT ?= out/demo

.PHONY: demo test setup clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[$(EXTRAS)]"
	touch $@

demo: $(STAMP)
	$(PY) -m sim info $(FLIGHT)
	$(PY) -m sim show $(FLIGHT) --frame 80 --out $(OUT)/frame-0080-truth.png
	$(PY) -m onboard telemetry $(FLIGHT)/telemetry.tlog --flight $(FLIGHT)
	$(PY) -m ground evaluate $(FLIGHT) --noise-px 1 --miss 0.1 --fp 0.5 --json $(OUT)/association.json
	@echo "demo outputs in $(OUT)/: frame-0080-truth.png (a frame, truth apples circled), association.json (counts, rows, errors)"

test: $(STAMP)
	$(PY) -m pytest

clean:
	rm -rf $(VENV) out .pytest_cache
