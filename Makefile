# KIWI: the two commands a newcomer types are `make demo` and `make test`.
SHELL := /bin/bash
.DEFAULT_GOAL := help

# System packages the build, the tools and the tests need (Debian names; chromium opens the session
# report page in its browser test; slurm-wlm and munge run `kiwi batch` on a single-node Slurm
# cluster in its test). `make deps` installs the missing ones.
APT_PACKAGES := libopencv-dev clang libclang-dev libudev-dev pkg-config ffmpeg openscad chromium slurm-wlm munge
# Python modules the export tests read datasets back with (independent readers), installed with
# pip for the `python3` on PATH: Debian 12 has no python3-pyarrow, and Debian's python3-* packages
# serve only /usr/bin/python3, which need not be the `python3` the tests run.
PY_MODULES := pyarrow pandas zarr pycolmap
# Only for `make hardware-renders` (OpenSCAD's PNG export needs an X display).
RENDER_PACKAGES := xvfb xauth
HARDWARE_OUT ?= build/hardware
DEMO_OUT ?= demo-out
DEMO_SEED ?= 7
DEMO_UNITS := X5-DEMO-L X5-DEMO-R
DEMO_RESOLUTION ?= 480
# A survey that builds the maps, then a tabletop and a walk episode (seconds each).
DEMO_DURATIONS ?= 20,5,6

.PHONY: help deps build demo test bench hardware hardware-renders clean

help:
	@echo "make demo   certify two simulated units, record a session with them and run kiwi run on it (installs what it needs)"
	@echo "make test   formatting, lints and every test"
	@echo "make bench  benchmarks (release build)"
	@echo "make deps   install the system packages the build needs (apt) and the Python modules the export tests read datasets with (pip)"
	@echo "make hardware  regenerate params.scad and the tool definitions, render every printed part to STL ($(HARDWARE_OUT)) and check it"
	@echo "make hardware-renders  the PNG renders in docs/hardware/ (installs xvfb)"

deps:
	@missing=""; for p in $(APT_PACKAGES); do dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing; \
	else echo "system packages present"; fi
	@missing=""; for m in $(PY_MODULES); do python3 -c "import $$m" 2>/dev/null || missing="$$missing $$m"; done; \
	if [ -z "$$missing" ]; then echo "Python modules present"; exit 0; fi; \
	echo "installing Python modules:$$missing"; \
	SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	if ! python3 -m pip --version >/dev/null 2>&1; then \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends python3-pip; \
	fi; \
	flags=""; \
	if python3 -c 'import os, sysconfig, sys; sys.exit(0 if os.path.exists(os.path.join(sysconfig.get_path("stdlib"), "EXTERNALLY-MANAGED")) else 1)'; then \
	  flags="--break-system-packages"; \
	fi; \
	python3 -m pip install --quiet --disable-pip-version-check $$flags $$missing || \
	  echo "WARNING: could not install the Python modules$$missing (pip failed; no network?): the export tests that read datasets back with Python will skip and say so"

build: deps
	cargo build --release --workspace --bins

# The demo's 480 px session has no head camera: the hat marker needs 960 px rear lenses
# (docs/head.md), and at 480 px every episode would be suspect for the head alone.
demo: build
	rm -rf $(DEMO_OUT) $(HARDWARE_OUT)
	@for unit in $(DEMO_UNITS); do \
	  ./target/release/kiwi-sim unit --out $(DEMO_OUT)/captures/$$unit --unit-id $$unit --seed $(DEMO_SEED) --resolution $(DEMO_RESOLUTION) --views 24 --cam-imu-duration 4 --static-hours 4 --static-rate 100 --bench-duration 0 --rig-duration 20 --rig-modes 30fps --rig-repeats 2 && \
	  ./target/release/kiwi-calib certify --unit $$unit --captures $(DEMO_OUT)/captures/$$unit --out $(DEMO_OUT)/units || exit 1; \
	done
	./target/release/kiwi-calib units list $(DEMO_OUT)/units
	./target/release/kiwi-sim session --out $(DEMO_OUT)/session --seed $(DEMO_SEED) --units $(DEMO_OUT)/units --left-unit X5-DEMO-L --right-unit X5-DEMO-R --scenario survey,tabletop,walk --episodes 3 --duration $(DEMO_DURATIONS) --resolution $(DEMO_RESOLUTION) --rate 29.97 --blur-samples 2 --no-head --workspace-markers
	./target/release/kiwi inspect $(DEMO_OUT)/session/session.toml
	./target/release/kiwi run --session $(DEMO_OUT)/session/session.toml
	./target/release/kiwi evaluate markers --session $(DEMO_OUT)/session/session.toml --episode ep001
	./target/release/kiwi report --session $(DEMO_OUT)/session/session.toml
	./target/release/kiwi-sim contact-sheet --out $(DEMO_OUT)/contact_sheet.png --seed $(DEMO_SEED) --tile 256
	@echo "demo: units X5-DEMO-L and X5-DEMO-R certified into $(DEMO_OUT)/units (reports: $(DEMO_OUT)/units/*/*/report/index.md)"
	@echo "demo: session in $(DEMO_OUT)/session; each episode's trajectories, TUM files and quality.json in $(DEMO_OUT)/session/episodes/<ep>/out/ (truth in its truth/ folder)"
	@echo "demo: the tabletop episode's accuracy against the two table markers: $(DEMO_OUT)/session/evaluation/markers-ep001.json"
	@echo "demo: the session's report page (open it in a browser): $(DEMO_OUT)/session/report/index.html"

test: deps
	cargo fmt --all -- --check
	cargo clippy --workspace --all-targets -- -D warnings
	@if command -v cargo-nextest >/dev/null 2>&1; then \
	  cargo nextest run --workspace --no-fail-fast; \
	else cargo test --workspace --no-fail-fast; fi
	cargo test --workspace --doc

bench: deps
	cargo bench -p kiwi-fixtures --bench render
	cargo bench -p kiwi-backend --bench sync
	cargo bench -p kiwi-calib --bench intrinsics
	cargo bench -p kiwi-calib --bench imu_noise
	cargo bench -p kiwi-calib --bench cam_imu
	cargo bench -p kiwi-calib --bench certify
	cargo bench -p kiwi-backend --bench fuse
	cargo bench -p kiwi-backend --bench vision
	cargo bench -p kiwi-backend --bench frames
	cargo bench -p kiwi-backend --bench export
	cargo bench -p kiwi-backend --bench head
	cargo bench -p kiwi-backend --bench floor

hardware: deps
	cargo run --release -p kiwi-calib -- hardware generate
	cargo run --release -p kiwi-calib -- hardware render --out $(HARDWARE_OUT)

# PNG renders of every part (in the pose it is used in) and of the assemblies, for docs/hardware.md.
hardware-renders: hardware
	@missing=""; for p in $(RENDER_PACKAGES); do dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing; fi
	mkdir -p docs/hardware
	set -e; for f in hardware/scad/parts/*.scad; do n=$$(basename $$f .scad); \
	  xvfb-run -a openscad --render -D "part=\"$$n\"" -o docs/hardware/$$n.png --imgsize=480,360 \
	    --colorscheme=Tomorrow --camera=220,260,160,0,0,0 --viewall --autocenter hardware/scad/renders/part.scad 2>/dev/null; done
	xvfb-run -a openscad -o docs/hardware/chopstick_assembly.png --imgsize=640,480 --colorscheme=Tomorrow \
	  --camera=260,260,80,0,40,-60 --viewall --autocenter hardware/scad/renders/chopstick_assembly.scad 2>/dev/null
	xvfb-run -a openscad -o docs/hardware/chopstick_open.png --imgsize=640,480 --colorscheme=Tomorrow -D half=chop_max_half_angle \
	  --camera=0,300,220,0,40,-60 --viewall --autocenter hardware/scad/renders/chopstick_assembly.scad 2>/dev/null
	xvfb-run -a openscad -o docs/hardware/parallel_jaw_assembly.png --imgsize=640,480 --colorscheme=Tomorrow \
	  --camera=260,260,80,0,40,-60 --viewall --autocenter hardware/scad/renders/parallel_jaw_assembly.scad 2>/dev/null
	xvfb-run -a openscad -o docs/hardware/robot_assembly.png --imgsize=640,480 --colorscheme=Tomorrow \
	  --camera=300,260,120,0,40,0 --viewall --autocenter hardware/scad/renders/robot_assembly.scad 2>/dev/null

clean:
	cargo clean
	rm -rf $(DEMO_OUT) $(HARDWARE_OUT)
