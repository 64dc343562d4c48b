# vlactl: every command a user needs. `make install` sets up .venv; `make test` runs the default (fast) tests.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
PIP := $(BIN)/python -m pip --disable-pip-version-check -q
export HF_HUB_OFFLINE := 1
export MUJOCO_GL ?= egl

.PHONY: install system-deps demo policies probes paper test test-slow test-real bench clean-venv

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(PIP) install --upgrade pip

# Mesa's EGL/OSMesa for CPU rendering, installed only when missing and only where we may (root + apt).
system-deps:
	@if ! ldconfig -p | grep -q 'libEGL_mesa\|libOSMesa'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    apt-get update -q && apt-get install -y -q libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6; \
	  else echo "warning: Mesa EGL/OSMesa not found; install libegl-mesa0 libgl1-mesa-dri (or libosmesa6) to render"; fi; \
	fi

install: $(BIN)/python system-deps
	$(PIP) install -c constraints.txt -e '.[dev]'
	# LeRobot 0.4.4 pins torch<2.11 (a multi-GB CUDA download); its code runs with ours, so install it alone.
	$(PIP) install --no-deps lerobot==0.4.4
	$(BIN)/vlactl --help >/dev/null && echo "vlactl installed in $(VENV)"

# The main job on the embedded default, small enough for a first run: list the suite, generate two demonstrations,
# run the shipped hybrid VLA closed loop on two episodes of each of two tasks, then one episode under height=high,
# enforced by the controller with the shipped probes (videos of both: the constrained one captioned with the window,
# the height against its bound and the push).
demo: install
	$(BIN)/vlactl tasks --suite libero_spatial
	$(BIN)/vlactl demos suite=libero_spatial tasks=[0] episodes_per_task=2 workers=1 output_dir=outputs/demo/libero_spatial
	$(BIN)/vlactl rollout model=hybrid suite=libero_spatial tasks=[0,1] episodes_per_task=2 workers=2 --video \
	  output_root=outputs/demo run_name=hybrid_libero_spatial
	$(BIN)/vlactl rollout --constraint height=high tasks=[0] episodes_per_task=1 workers=1 --video \
	  output_root=outputs/demo run_name=hybrid_libero_spatial_height-high

# Rebuild the shipped embedded models from scratch: the libero_spatial demo sets, then each model trained with its
# own config (conf/model/<name>.yaml) on DATASET_<name>, then each of its STAGES_<name> in order: a fine-tune of the
# checkpoint so far with TUNE_<name>_<stage>'s options, and for a stage written `<stage>+soup` the uniform average of
# that fine-tune's weights and those it started from (`vlactl average-policies`, a model soup), which becomes the
# checkpoint so far; the last one is copied into data/policies/, then the probes that ship beside them.
# The autoregressive model learns from the 50 ordinary episodes per task plus 30 noise-injected (DART) ones, trains a
# second cosine cycle, then is fine-tuned on a perturbation-weighted set that keeps the DART noise (10 ordinary, 10
# noise-injected, 20 perturbed a task) and averaged with its start, then DAgger on its own perturbed states (that set
# beside its rollouts taken over by raise, close, slow and shift, replayed and handed to the expert), averaged again,
# then a second such round on that average's own states after a raise and a closed gripper, averaged once more, then a
# third weighted to the closed gripper, averaged again.
# The hybrid is fine-tuned on recovery demonstrations, then on perturbed ones (the expert's way back after the arm was
# raised, held, shifted, slowed or its gripper closed, beside ordinary and recovery episodes), averaged with its start,
# then fine-tuned on a set weighted to perturbed episodes and averaged again, then on the expert's way back from the
# states its own steered stop leaves (DAgger) and averaged once more, then a second DAgger round on the stops of both
# pausing constraints, averaged the same way, then DAgger on the perturbations (the policy's own states after the arm
# was raised, closed, turned, slowed or shifted, and its own pausing stops), averaged again, then a second such round on
# that average's own perturbed states (raised, closed, slowed, shifted), averaged again: each fine-tune alone loses
# tasks the checkpoint before solved, the average keeps them and most of the way back it learned (docs/models.md). The
# robust3 perturbed set is also what the shipped probes are fitted on.
# Every step resumes where it stopped when re-run.
POLICIES ?= hybrid autoregressive
DATASET_hybrid ?= data/demos/libero_spatial
DATASET_autoregressive ?= data/demos/libero_spatial_noisy
STAGES_autoregressive ?= continued noisyrobust+soup dagger+soup dagger2+soup dagger3+soup
TUNE_autoregressive_continued ?= dataset=$(DATASET_autoregressive) steps=7000 lr=2e-4 warmup_steps=200
TUNE_autoregressive_noisyrobust ?= dataset=data/demos/libero_spatial_noisy_robust steps=4000 lr=1e-4 warmup_steps=200
TUNE_autoregressive_dagger ?= dataset=data/demos/libero_spatial_noisy_dagger steps=4000 lr=1e-4 warmup_steps=200
TUNE_autoregressive_dagger2 ?= dataset=data/demos/libero_spatial_noisy_dagger2 steps=4000 lr=1e-4 warmup_steps=200
TUNE_autoregressive_dagger3 ?= dataset=data/demos/libero_spatial_noisy_dagger3 steps=2000 lr=1e-4 warmup_steps=100
STAGES_hybrid ?= continued robust+soup robust3+soup dagger+soup dagger4+soup dagger6+soup dagger7+soup
TUNE_hybrid_continued ?= dataset=data/demos/libero_spatial_recovery steps=4000 lr=1e-4 warmup_steps=200
TUNE_hybrid_robust ?= dataset=data/demos/libero_spatial_robust steps=4000 lr=1e-4 warmup_steps=200
TUNE_hybrid_robust3 ?= dataset=data/demos/libero_spatial_robust3 steps=4000 lr=1e-4 warmup_steps=200
TUNE_hybrid_dagger ?= dataset=data/demos/libero_spatial_dagger steps=4000 lr=1e-4 warmup_steps=200
TUNE_hybrid_dagger4 ?= dataset=data/demos/libero_spatial_dagger4 steps=4000 lr=1e-4 warmup_steps=200
TUNE_hybrid_dagger6 ?= dataset=data/demos/libero_spatial_dagger6 steps=4000 lr=1e-4 warmup_steps=200
TUNE_hybrid_dagger7 ?= dataset=data/demos/libero_spatial_dagger7 steps=4000 lr=1e-4 warmup_steps=200
# The checkpoint so far under control+pause with its own probes (constraint, window, episodes a task), cut at the window,
# on init states from 10 (evaluations use 0-9): the stops a DAgger round replays, in $(current)/stops-<constraint>.
define stop_runs
	$(BIN)/vlactl rollout model=$(current)/checkpoint probes=$(current)/probes/steer stop_probes=$(current)/probes/stop \
	  constraint=$(1) method=control pause=true first_episode=10 episodes_per_task=$(3) max_steps=$(2) workers=2 \
	  output_root=$(current) run_name=stops-$(subst =,-,$(1))
endef
# A stage's demonstrations made from the checkpoint so far (`current`), before its fine-tune: PREPARE_<model>_<stage>.
# DAgger on the pushed stop: probes fitted on the checkpoint so far, its control+pause height=high rollouts cut at 15
# steps (the window and the stop it leaves), and each replayed from the same start and handed to the expert (15 a
# task, init states 10-24; evaluations use 0-9) beside robust3's episodes. About 70 min on 2 cores.
define PREPARE_hybrid_dagger
	$(call fit_probes,$(current)/checkpoint,$(PROBE_DEMOS),$(current)/probes)
	$(call stop_runs,height=high,15,15)
	$(call extended_demos,data/demos/libero_spatial_dagger,episodes_per_task=10 recovery_episodes_per_task=5 \
	  perturbed_episodes_per_task=20 replayed_episodes_per_task=15 replay_from=$(current)/stops-height-high,\
	  data/demos/libero_spatial_robust3)
endef
# The stops of both pausing constraints (height=high's 15 steps, speed=low's 25) from the checkpoint so far under probes
# fitted on it, 10 rollouts a task each (init states 10-19), and the list of their run folders for replay_from.
define pausing_stops
	$(call fit_probes,$(current)/checkpoint,$(PROBE_DEMOS),$(current)/probes)
	$(call stop_runs,height=high,15,10)
	$(call stop_runs,speed=low,25,10)
endef
pausing_stop_runs = $(current)/stops-speed-low$(comma)$(current)/stops-height-high
# A second DAgger round on both pausing stops, 5 replays a task from each beside robust3's episodes: a smaller share of
# replays than the first round's, which kept unconstrained success where a full share lost it (docs/models.md). About 55 min.
define PREPARE_hybrid_dagger4
	$(pausing_stops)
	$(call extended_demos,data/demos/libero_spatial_dagger4,episodes_per_task=10 recovery_episodes_per_task=5 \
	  perturbed_episodes_per_task=20 replayed_episodes_per_task=5 replay_from=[$(pausing_stop_runs)],\
	  data/demos/libero_spatial_robust3)
endef
# The checkpoint so far taken over for its first 15 steps by each of the given perturbation kinds, 5 rollouts a task
# (init states 10-14, or from the first episode given second) cut at step 40: the runs a perturbation DAgger round
# replays, in $(current)/perturb-<kind>[-<first episode>].
define perturb_runs
	$(foreach k,$(1),$(BIN)/vlactl rollout model=$(current)/checkpoint perturb=$(k) first_episode=$(or $(2),10) \
	  episodes_per_task=5 max_steps=40 workers=2 output_root=$(current) run_name=perturb-$(k)$(if $(2),-$(2))
	)
endef
perturb_run_list = $(call join_commas,$(foreach k,$(1),$(current)/perturb-$(k)$(if $(2),-$(2))))
# perturb_runs, and their folders appended to the replay list named $(3): a DAgger round replays its own runs beside
# every earlier round's.
define replayed_perturb_runs
	$(call perturb_runs,$(1),$(2))
	$(eval $(3) := $($(3))$(comma)$(call perturb_run_list,$(1),$(2)))
endef
# DAgger on the perturbations (docs/models.md): perturb_runs of the kinds it came back from least often
# (PERTURB_REPLAYED) and its own pausing stops, each replayed and handed to the expert, 5 a task from each beside
# robust3's episodes. About 110 min on 2 cores. dagger6_replays keeps the list for the next round.
PERTURB_REPLAYED ?= raise close tilt slow shift
define PREPARE_hybrid_dagger6
	$(pausing_stops)
	$(call perturb_runs,$(PERTURB_REPLAYED))
	$(eval dagger6_replays := $(pausing_stop_runs)$(comma)$(call perturb_run_list,$(PERTURB_REPLAYED)))
	$(call extended_demos,data/demos/libero_spatial_dagger6,episodes_per_task=10 recovery_episodes_per_task=5 \
	  perturbed_episodes_per_task=20 replayed_episodes_per_task=5 replay_from=[$(dagger6_replays)],\
	  data/demos/libero_spatial_robust3)
endef
# The autoregressive model's DAgger on the perturbations: its perturb_runs of PERTURB_REPLAYED_autoregressive, each
# replayed and handed to the expert, 5 a task from each beside the noisy_robust set's episodes. About 45 min.
PERTURB_REPLAYED_autoregressive ?= raise close slow shift
define PREPARE_autoregressive_dagger
	$(call perturb_runs,$(PERTURB_REPLAYED_autoregressive))
	$(eval ar_dagger_replays := $(call perturb_run_list,$(PERTURB_REPLAYED_autoregressive)))
	$(call extended_demos,data/demos/libero_spatial_noisy_dagger,$(noisy_dagger_set) replay_from=[$(ar_dagger_replays)],\
	  data/demos/libero_spatial_noisy_robust)
endef
noisy_dagger_set = episodes_per_task=10 noisy_episodes_per_task=10 perturbed_episodes_per_task=20 \
  replayed_episodes_per_task=5
# A second round on that average's own states after a raise (init states 15-19) and a closed gripper (15-19 and
# 20-24), replayed beside the first round's runs (docs/models.md). About 35 min.
define PREPARE_autoregressive_dagger2
	$(eval ar_dagger2_replays := $(ar_dagger_replays))
	$(call replayed_perturb_runs,raise close,15,ar_dagger2_replays)
	$(call replayed_perturb_runs,close,20,ar_dagger2_replays)
	$(call extended_demos,data/demos/libero_spatial_noisy_dagger2,$(noisy_dagger_set) replay_from=[$(ar_dagger2_replays)],\
	  data/demos/libero_spatial_noisy_dagger)
endef
# A third round weighted to the closed gripper: that average's own states after close (init states 25-29 and 30-34) and
# a raise (20-24), replayed beside the first two rounds' runs; a 2000-step fine-tune, to stay near two hours of
# training (docs/models.md). About 40 min.
define PREPARE_autoregressive_dagger3
	$(eval ar_dagger3_replays := $(ar_dagger2_replays))
	$(call replayed_perturb_runs,close,25,ar_dagger3_replays)
	$(call replayed_perturb_runs,close,30,ar_dagger3_replays)
	$(call replayed_perturb_runs,raise,20,ar_dagger3_replays)
	$(call extended_demos,data/demos/libero_spatial_noisy_dagger3,$(noisy_dagger_set) replay_from=[$(ar_dagger3_replays)],\
	  data/demos/libero_spatial_noisy_dagger2)
endef
# A second round on the perturbations the dagger6 checkpoint still came back from least often (PERTURB_REPLAYED_AGAIN):
# its perturb_runs replayed beside dagger6's, 5 a task from each (docs/models.md, "A second DAgger round"). About 30 min.
PERTURB_REPLAYED_AGAIN ?= raise close shift slow
define PREPARE_hybrid_dagger7
	$(call perturb_runs,$(PERTURB_REPLAYED_AGAIN))
	$(call extended_demos,data/demos/libero_spatial_dagger7,episodes_per_task=10 recovery_episodes_per_task=5 \
	  perturbed_episodes_per_task=20 replayed_episodes_per_task=5 replay_from=[$(dagger6_replays)$(comma)$(call \
	  perturb_run_list,$(PERTURB_REPLAYED_AGAIN))],data/demos/libero_spatial_dagger6)
endef
# One stage (model, stage[+soup]); `current` is the checkpoint folder so far, advanced as the recipe expands: the
# fine-tune's folder outputs/policies/<model>-<stage>, or its average's, outputs/policies/<model>-<stage>-soup.
stage_name = $(firstword $(subst +, ,$(1)))
define train_stage
	$(PREPARE_$(1)_$(call stage_name,$(2)))
	$(BIN)/vlactl train-policy model=$(1) init_from=$(current)/checkpoint $(TUNE_$(1)_$(call stage_name,$(2))) \
	  output_dir=outputs/policies/$(1)-$(call stage_name,$(2))
	$(if $(findstring +soup,$(2)),$(BIN)/vlactl average-policies output_dir=outputs/policies/$(1)-$(subst +,-,$(2)) \
	  policies=[$(current)/checkpoint$(comma)outputs/policies/$(1)-$(call stage_name,$(2))/checkpoint])
	$(eval current := outputs/policies/$(1)-$(subst +,-,$(2)))
endef
define train_policy
	$(BIN)/vlactl train-policy model=$(1) dataset=$(DATASET_$(1)) output_dir=outputs/policies/$(1)
	$(eval current := outputs/policies/$(1))
	$(foreach stage,$(STAGES_$(1)),$(call train_stage,$(1),$(stage)))
	rm -rf data/policies/$(1).new && cp -r $(current)/checkpoint \
	  data/policies/$(1).new && rm -rf data/policies/$(1) && mv data/policies/$(1).new data/policies/$(1)

endef
# A set that extends data/demos/libero_spatial (or the set named third) starts from hard links to its staged episodes,
# so the sets share their episodes (as the measured ones do) and only the extra kinds are simulated.
define extended_demos
	mkdir -p $(1).staging && cp -aln $(or $(3),data/demos/libero_spatial).staging/. $(1).staging/
	$(BIN)/vlactl demos suite=libero_spatial $(2) workers=2 output_dir=$(1)
endef
policies: install
	$(BIN)/vlactl demos suite=libero_spatial episodes_per_task=50 workers=2
	$(call extended_demos,data/demos/libero_spatial_recovery,episodes_per_task=20 recovery_episodes_per_task=25)
	$(call extended_demos,data/demos/libero_spatial_noisy,episodes_per_task=50 noisy_episodes_per_task=30)
	$(call extended_demos,data/demos/libero_spatial_noisy_robust,episodes_per_task=10 noisy_episodes_per_task=10 \
	  perturbed_episodes_per_task=20)
	$(call extended_demos,data/demos/libero_spatial_probe,episodes_per_task=4)
	$(call extended_demos,data/demos/libero_spatial_robust,episodes_per_task=10 recovery_episodes_per_task=10 \
	  perturbed_episodes_per_task=12)
	$(call extended_demos,data/demos/libero_spatial_robust3,episodes_per_task=10 recovery_episodes_per_task=5 \
	  perturbed_episodes_per_task=20)
	$(foreach m,$(POLICIES),$(call train_policy,$(m)))
	$(MAKE) probes

# The probes that ship beside each model in data/probes/<model>/ (found by `vlactl rollout --constraint ...` by
# default), made by fit_probes (model and its options, demonstrations, folder, train-probes options): activations
# (every 4th frame, or PROBE_COLLECT_<model>), the observability probes (observe/: every feature, the best ridge
# penalty) and the steering probes (steer/: the action read-outs the constraints push): one candidate run per
# STEER_FAMILIES (fit: ridge / logistic with STEER_PROBE_ARGS' strong penalties; meandiff, covariance: a direction
# and its scale), each measured by `vlactl controllability`, and per feature the run whose push moves the predicted
# action most (docs/steering.md); and the stop probes (stop/: the read-outs `pause=true` stops the arm with, fitted
# with the other action features regressed out, so that a stopped translation does not tilt the hand). About 8 min a
# model on 2 idle cores (20 beside other jobs).
PROBE_DEMOS ?= data/demos/libero_spatial_robust3
PROBE_COLLECT ?= every=4
# The autoregressive model's probes read where it writes its actions (its decode steps: `pooling=action`; a push on the
# prompt's read-out barely reaches its decoded tokens), fitted on 4 ordinary episodes a task (docs/steering.md).
PROBE_DEMOS_autoregressive ?= data/demos/libero_spatial_probe
PROBE_COLLECT_autoregressive ?= every=2 pooling=action
STEER_FEATURES ?= [dx,dy,dz,dyaw,speed,gripper_action]
STEER_PROBE_ARGS ?= ridge_grid=[1000000] logistic_l2=1e4
STEER_FAMILIES ?= fit meandiff covariance
CHOOSE_ARGS ?= frames=16 batch_size=16 targets=[-1,1]  # 16 frames x 2 pushes a unit: ~8 min a family on 2 busy cores
STOP_PROBE_FEATURES ?= [dx,dy,dz,droll,dpitch,dyaw,speed,gripper_action]  # each fitted with the others regressed out
comma := ,
join_commas = $(subst $(eval) ,$(comma),$(strip $(1)))
define fit_probes
	$(BIN)/vlactl collect model=$(1) dataset=$(2) output_dir=$(3)/activations \
	  $(or $(PROBE_COLLECT_$(firstword $(1))),$(PROBE_COLLECT))
	$(BIN)/vlactl train-probes activations=$(3)/activations output_dir=$(3)/observe $(4)
	$(foreach f,$(STEER_FAMILIES),$(BIN)/vlactl train-probes activations=$(3)/activations output_dir=$(3)/steer-$(f) \
	  features=$(STEER_FEATURES) family=$(f) $(STEER_PROBE_ARGS) $(4)
	)
	$(BIN)/vlactl controllability model=$(1) dataset=$(2) choose_into=$(3)/steer $(CHOOSE_ARGS) \
	  probes=[$(call join_commas,$(foreach f,$(STEER_FAMILIES),$(3)/steer-$(f)))]
	$(BIN)/vlactl train-probes activations=$(3)/activations output_dir=$(3)/stop features=$(STOP_PROBE_FEATURES) \
	  family=partial $(STEER_PROBE_ARGS) $(4)
	$(BIN)/vlactl controllability model=$(1) dataset=$(2) probes=$(3)/stop features=[dx,dy,dz,dyaw] $(CHOOSE_ARGS)
endef
# each build in a folder of its weights' own (a retrained model's activations must not resume the last build's), named
# by the fingerprint the probes record (`weights` in their provenance: sha256 of the weights, 16 digits)
weights_id = $(shell sha256sum data/policies/$(1)/model.safetensors | cut -c1-16)
define build_probes
	$(eval build := outputs/probes-build/$(1)-$(call weights_id,$(1)))
	$(call fit_probes,$(1),$(or $(PROBE_DEMOS_$(1)),$(PROBE_DEMOS)),$(build))
	rm -rf data/probes/$(1).new && mkdir -p data/probes/$(1).new && for f in observe steer stop; do \
	  mkdir -p data/probes/$(1).new/$$f && cp -r $(build)/$$f/probes \
	  $(build)/$$f/*.parquet $(build)/$$f/*.json $(build)/$$f/config.yaml \
	  data/probes/$(1).new/$$f/; done && rm -rf data/probes/$(1) && mv data/probes/$(1).new data/probes/$(1)

endef
probes: install
	$(foreach m,$(POLICIES),$(call build_probes,$(m)))

# The paper's whole protocol on one model (default: the embedded hybrid) into $(PAPER_DIR): activations and probes
# (fit_probes: observe/, the chosen steering probes steer/ and the stop probes stop/) and Fig. 1, sweep and Fig. 2, readings and Fig. 3,
# rollouts (unconstrained, then every constraint x method: control bounds the action the policy is about to take with
# the steering probes, alpha and meandiff push along them, filter is the action-space oracle) and Figs. 4-8 with
# summary.md. Every stage resumes when re-run; any stage can be re-run alone from the one before.
# method=none acts as the unconstrained policy does, so its runs judge the unconstrained run's episodes (judge_from=),
# except under gripper=closed, where the baselines start with the gripper closed (the paper's favourable start).
PAPER_MODEL ?= hybrid
PAPER_DIR ?= outputs/paper/$(PAPER_MODEL)
PAPER_EPISODES ?= 10
PAPER_DEMOS ?= data/demos/libero_spatial
PAPER_CONSTRAINTS ?= gripper=open gripper=closed height=low height=high speed=low speed=high
PAPER_METHODS ?= none prompt control control+pause alpha meandiff filter filter+pause  # <m>+pause: method=<m> pause=true
PAPER_ARGS ?=
PAPER_MODEL_ARGS ?=  # a real model's options, e.g. model.checkpoint=lerobot/pi05_libero (docs/real-models.md)
PAPER_PROBE_ARGS ?=  # train-probes options for every probe set, e.g. device=cuda
paper:
	$(call fit_probes,$(PAPER_MODEL) $(PAPER_MODEL_ARGS),$(PAPER_DEMOS),$(PAPER_DIR),$(PAPER_PROBE_ARGS))
	$(BIN)/vlactl plot probes run_dir=$(PAPER_DIR)/observe
	$(BIN)/vlactl sweep model=$(PAPER_MODEL) $(PAPER_MODEL_ARGS) probes=$(PAPER_DIR)/observe output_dir=$(PAPER_DIR)/sweep
	$(BIN)/vlactl plot sweep run_dir=$(PAPER_DIR)/sweep
	$(BIN)/vlactl plot readings model=$(PAPER_MODEL) $(PAPER_MODEL_ARGS) probes=$(PAPER_DIR)/observe
	$(BIN)/vlactl rollout model=$(PAPER_MODEL) $(PAPER_MODEL_ARGS) episodes_per_task=$(PAPER_EPISODES) output_root=$(PAPER_DIR)/rollouts $(PAPER_ARGS)
	for c in $(PAPER_CONSTRAINTS); do for m in $(PAPER_METHODS); do \
	  case $$c/$$m in gripper=*/*+pause|speed=high/*+pause) continue;; esac; \
	  judge=$$([ $$m = none ] && [ $$c != gripper=closed ] && echo judge_from=$(PAPER_DIR)/rollouts/$(PAPER_MODEL)_libero_spatial); \
	  $(BIN)/vlactl rollout model=$(PAPER_MODEL) $(PAPER_MODEL_ARGS) constraint=$$c method=$${m%+pause} \
	    $$(case $$m in control+pause) echo pause=true stop_probes=$(PAPER_DIR)/stop;; *+pause) echo pause=true;; esac) \
	    probes=$(PAPER_DIR)/steer \
	    activations=$(PAPER_DIR)/activations demos=$(PAPER_DEMOS) episodes_per_task=$(PAPER_EPISODES) \
	    output_root=$(PAPER_DIR)/rollouts $$judge $(PAPER_ARGS) || exit 1; done; done
	$(BIN)/vlactl plot rollouts root=$(PAPER_DIR)/rollouts output_dir=$(PAPER_DIR)/figures

# Two pytest workers, a test file each (its module fixtures built once): 6.5 min on 2 cores against 12.8 in one process,
# whose time goes mostly to loading the simulator and single-threaded rollouts.
test:
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

test-slow:
	$(BIN)/python -m pytest -q -m slow

# The real-model tests with π0.5 on openpi's transformers branch (PyPI's transformers-openpi, imported as
# `transformers`): .venv keeps transformers 4.57 for everything else, so the branch and the tokenizers it needs go into
# a folder of their own, first on PYTHONPATH over .venv (118 MB against a second 8 GB environment). Re-running reuses it
# (reinstalled when requirements-pi05.txt changes). Not `.[pi05]`: LeRobot's torch<2.11 pin.
PI05_SITE := .pi05-site
$(PI05_SITE)/.installed: requirements-pi05.txt | $(BIN)/python
	rm -rf $(PI05_SITE) && $(PIP) install --no-deps --target $(PI05_SITE) -r requirements-pi05.txt
	touch $@

test-real: $(PI05_SITE)/.installed
	PYTHONPATH=$(PI05_SITE) $(BIN)/python -m pytest -q tests/test_real_models.py

bench:
	@for f in benchmarks/bench_*.py; do echo "== $$f"; $(BIN)/python $$f || exit 1; done
