# The two commands of README.md: `make demo` and `make test`. Each sets up its own
# virtual environment (idempotent: it reinstalls only when pyproject.toml changes).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# the demo needs no torch; the tests also cover training/export (torch, torchvision: the export extra)
EXTRAS ?= onboard,ground,sim,dev
TEST_EXTRAS ?= onboard,ground,sim,export,dev
comma := ,
STAMP := $(VENV)/.installed-$(subst $(comma),-,$(EXTRAS))
TEST_STAMP := $(VENV)/.installed-$(subst $(comma),-,$(TEST_EXTRAS))
FLIGHT ?= replay_data/demo-flight
OUT ?= out/demo

.PHONY: demo test setup clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[$(EXTRAS)]"
	touch $@

$(TEST_STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[$(TEST_EXTRAS)]"
	touch $@

# The bundled flight through both processes (onboard: ONNX detector; ground: registration,
# association, map files, rerun recording), then its evaluation against the flight's truth.
demo: $(STAMP)
	$(PY) -m ground replay $(FLIGHT) --out $(OUT)

test: $(TEST_STAMP)
	$(PY) -m pytest

clean:
	rm -rf $(VENV) out .pytest_cache
