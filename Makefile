# make demo: create .venv, install, run the main job on small defaults.
# make test: create .venv, install with test extras, run the test suite.
PYTHON ?= python3
VENV := .venv
PIP := $(VENV)/bin/pip
PY := $(VENV)/bin/python
DEMO_OUT ?= runs/demo
# test processes (pytest-xdist), each test file in one of them: one per core of CI's 2-core machine
TEST_WORKERS ?= 2

.PHONY: demo test install install-test clean

$(VENV)/bin/activate:
	$(PYTHON) -m venv $(VENV)
	$(PIP) install --upgrade pip

# torch is pinned and installed first so that the CPU wheel is used.
$(VENV)/.installed: $(VENV)/bin/activate pyproject.toml
	$(PIP) install torch==2.13.0
	$(PIP) install -e .
	touch $@

$(VENV)/.installed-test: $(VENV)/.installed
	$(PIP) install -e '.[test]'
	touch $@

install: $(VENV)/.installed
install-test: $(VENV)/.installed-test

demo: $(VENV)/.installed
	$(VENV)/bin/quadformer demo --out $(DEMO_OUT)

test: $(VENV)/.installed-test
	$(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile

clean:
	rm -rf $(VENV) runs build *.egg-info src/*.egg-info
