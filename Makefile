# Two entry points for a fresh machine: `make demo` and `make test`.
# Both install what they need (libllvm19 via apt when missing, .venv, mi_grg).
VENV  ?= .venv
PY    := $(VENV)/bin/python
STAMP := $(VENV)/.mi_grg-installed

.PHONY: demo test test-slow bench setup clean

$(STAMP): pyproject.toml scripts/setup.sh
	VENV=$(VENV) bash scripts/setup.sh
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/mi-grg demo --out out/demo

test: $(STAMP)
	$(PY) -m pytest -m "not slow" -q

test-slow: $(STAMP)
	$(PY) -m pytest -m slow -q

bench: $(STAMP)
	$(PY) bench/projector.py
	$(PY) bench/baselines.py
	$(PY) bench/voxelizer.py
	$(PY) bench/graph.py
	$(PY) bench/train_step.py
	$(PY) bench/packets.py
	$(PY) bench/stop_rule.py

clean:
	rm -rf $(VENV) out build *.egg-info
