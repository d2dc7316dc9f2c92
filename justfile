# Crater-based absolute navigation: one recipe per stage, plus run, sweep, campaign, test, bench, sql, view.
# Recipes use the project's virtual environment (.venv) when it exists.

set positional-arguments
export PATH := justfile_directory() / ".venv/bin" + ":" + env("PATH")

py := "python -m pipeline"

# list the recipes
default:
    @just --list

# every stage on a scenario (default: the paper's case on the synthetic catalogue)
run *args:
    {{py}} run "$@"

# stage 1: ingest a crater catalogue into catalogue/craters.duckdb (e.g. --source ../shared/data/robbins2018_ge20km.csv)
ingest *args:
    {{py}} ingest "$@"

# stage 2: propagate the descent to impact
trajectory *args:
    {{py}} trajectory "$@"

# stage 2b: the IMU (100 Hz increments) and the laser altimeter, from the true descent
imu *args:
    {{py}} imu "$@"

# stage 2c: the camera's rendered images of chosen frames and the craters detected in them
render *args:
    {{py}} render "$@"

# stage 3: visible, detected and identified craters, used, and their measurements
detect *args:
    {{py}} detect "$@"

# stage 3b: the closed loop (powered descent flown on the navigator's estimate; default scenario: landing)
fly *args:
    {{py}} fly "$@"

# stage 4: pose estimation (the paper's method and the joint ML)
estimate *args:
    {{py}} estimate "$@"

# stage 4b: the navigation filter (error-state EKF: IMU + craters + altimeter)
navigate *args:
    {{py}} navigate "$@"

# stage 5: scores, CRLB and report.md
score *args:
    {{py}} score "$@"

# the stages as declared: config, inputs, outputs and the code each is keyed on
stages:
    {{py}} stages

# the crater-cap sweep: the paper's Table 1, a campaign over caps x seeds (both methods per run)
sweep *args:
    {{py}} sweep "$@"

# compare runs side by side (e.g. just compare default camera south-pole bearings-only)
compare *args:
    {{py}} compare "$@"

# a Monte Carlo campaign on Ray (e.g. just campaign dispersed --workers 2; --address for a cluster)
campaign *args:
    {{py}} campaign "$@"

# read-only SQL over the catalogue (add --run RUN for a run's tables, --campaign NAME a campaign's)
sql *args:
    {{py}} sql "$@"

# open a run's (or a campaign's) recordings in the Rerun viewer
view run="default" *args:
    {{py}} view "$@"

# craters in your own images: just detect-image IMAGE... --out DIR [--sun-azimuth-deg A] [--detector classical|learned] [--labels FILE]
detect-image *args:
    {{py}} detect-image "$@"

# train the learned crater detector (needs the `train` extra: pip install -e ".[train]"); --loo DIR for the leave-one-image-out folds
train-detector *args:
    python -m pipeline.train "$@"

# the test suite (uses both cores: one pytest worker each, single-threaded BLAS so they do not
# fight), but the tests marked slow (long end-to-end and real-catalogue checks: `just test-slow`,
# both run in CI)
test *args:
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 python -m pytest -n 2 --dist loadscope -m "not slow and not targets" "$@"

# the tests marked slow
test-slow *args:
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 python -m pytest -n 2 --dist loadscope -m "slow and not targets" "$@"

# the learned detector's accuracy targets (rendered and real; they fail until a model meets them)
test-targets *args:
    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 python -m pytest -n 2 --dist loadscope -m targets "$@"

# benchmarks: figures printed and saved to runs/bench/
bench *args:
    {{py}} bench "$@"

# lint
lint:
    ruff check pipeline tests

# lint, types (all of pipeline/) and the import contract: what CI and pre-commit run
check:
    ruff check pipeline tests
    mypy
    lint-imports
