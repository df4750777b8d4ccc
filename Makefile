# Two entry points a newcomer needs:  `make demo`  and  `make test`.
# Both create the virtual environment and install everything first (system packages too).
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test install

$(STAMP): pyproject.toml tools/install.sh
	bash tools/install.sh $(VENV)
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/slam synth runs/demo_data --scenario scanning --frames 100 --size 320x256 --seed 7
	$(VENV)/bin/slam run runs/demo_data --mode frame2model --out runs/demo --overwrite

test: $(STAMP)
	$(PY) -m pytest -q -n auto --dist loadfile
