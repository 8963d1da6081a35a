#!/usr/bin/env bash
# A whole scatterfarm farm on this machine, every process on its own "host": a coordinator and N
# workers, each in its own network namespace with its own address on a private bridge, talk
# gRPC over that bridge with a token. The script submits a small job from a client namespace,
# follows it to the end, fetches the result, checks that every worker rendered some of it, stops
# the farm as an operator would (SIGTERM: workers finish their task, the coordinator drains)
# and removes everything it created (namespaces, bridge, processes, temporary files), also when
# interrupted or when a step fails.
#
# Usage (as root; needs iproute2's `ip`):
#   deploy/local-cluster.sh [BINARY] [--workers N] [--engine cpu|gpu|auto] [--subnet A.B.C]
#                           [--timeout SECONDS] [--keep DIR]
#
#   BINARY / --binary PATH   the scatterfarm binary (else $SCATTERFARM_BIN, else
#                            target/release/scatterfarm)
#   --workers N              how many workers (else $SCATTERFARM_WORKERS, default 2)
#   --engine E               the workers' engine (else $SCATTERFARM_ENGINE, default cpu: works
#                            anywhere; gpu uses lavapipe on a machine without a GPU)
#   --subnet A.B.C           the /24 of the private bridge (else $SCATTERFARM_CLUSTER_SUBNET,
#                            default 10.77.0): coordinator .1, workers .11, .12, ..., client .100
#   --timeout SECONDS        bound on each client command, `watch` included (else
#                            $SCATTERFARM_CLUSTER_TIMEOUT, 600)
#   --keep DIR               copy the result, the job file and every log to DIR before cleaning up
#
# The topology: one namespace "sw" holds the bridge (so the host's own network namespace, its
# routes and its firewall are never touched, and two runs at once do not collide); namespaces
# "coord", "w1".."wN" and "client" each hold one end of a veth pair whose other end is a bridge
# port. Namespace names carry this script's process id (sfc<PID>-...).
#
# Exit status: 0 when the job finished and every worker rendered part of it; 1 on a failure;
# 2 on a usage error; 77 when this machine cannot run it (not root, no `ip`, no network
# namespaces).

set -Eeuo pipefail

script_dir=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
repo_dir=$(cd "$script_dir/.." && pwd)

binary=${SCATTERFARM_BIN:-}
workers=${SCATTERFARM_WORKERS:-2}
engine=${SCATTERFARM_ENGINE:-cpu}
subnet=${SCATTERFARM_CLUSTER_SUBNET:-10.77.0}
timeout_s=${SCATTERFARM_CLUSTER_TIMEOUT:-600}
keep_dir=

log() { printf '[local-cluster] %s\n' "$*" >&2; }
die() {
    log "FAILED: $*"
    exit 1
}
usage() {
    sed -n '2,/^$/{s/^# \{0,1\}//;p}' "${BASH_SOURCE[0]}" >&2
    exit "${1:-2}"
}

while (($#)); do
    case $1 in
    -h | --help) usage 0 ;;
    -b | --binary) binary=${2:?--binary needs a path}; shift 2 ;;
    -n | --workers) workers=${2:?--workers needs a number}; shift 2 ;;
    --engine) engine=${2:?--engine needs cpu, gpu or auto}; shift 2 ;;
    --subnet) subnet=${2:?--subnet needs A.B.C}; shift 2 ;;
    --timeout) timeout_s=${2:?--timeout needs seconds}; shift 2 ;;
    --keep) keep_dir=${2:?--keep needs a folder}; shift 2 ;;
    -*) log "unknown option $1"; usage 2 ;;
    *)
        [[ -z $binary ]] || { log "one binary only (got $binary and $1)"; usage 2; }
        binary=$1
        shift
        ;;
    esac
done

[[ $workers =~ ^[1-9][0-9]?$ && $workers -le 80 ]] || { log "--workers must be 1..80, got $workers"; exit 2; }
[[ $engine =~ ^(cpu|gpu|auto)$ ]] || { log "--engine must be cpu, gpu or auto, got $engine"; exit 2; }
[[ $subnet =~ ^([0-9]{1,3})\.([0-9]{1,3})\.([0-9]{1,3})$ ]] || { log "--subnet must look like 10.77.0, got $subnet"; exit 2; }
[[ $timeout_s =~ ^[1-9][0-9]*$ ]] || { log "--timeout must be a whole number of seconds, got $timeout_s"; exit 2; }

# What this machine must offer.
if [[ $(id -u) -ne 0 ]]; then
    log "SKIPPED: must run as root (network namespaces and veth pairs need CAP_NET_ADMIN)"
    exit 77
fi
command -v ip >/dev/null || { log "SKIPPED: iproute2's ip is missing (apt-get install iproute2)"; exit 77; }
if [[ -z $binary ]]; then
    binary=target/release/scatterfarm
    [[ -x $binary ]] || binary=$repo_dir/target/release/scatterfarm
fi
[[ -x $binary ]] || die "no executable scatterfarm binary at $binary (cargo build --release, or pass its path)"
binary=$(cd "$(dirname "$binary")" && pwd)/$(basename "$binary")
"$binary" worker --help >/dev/null 2>&1 || die "$binary has no worker subcommand"

# Everything created is recorded here, and only that is removed.
tag=sfc$$
namespaces=()
pids=()         # farm processes (coordinator, workers), killed last
client_pids=()  # client commands running in the background
work=
cleaned=0

cleanup() {
    local rc=$?
    ((cleaned)) && return 0
    cleaned=1
    trap - EXIT INT TERM
    set +e
    local pid ns
    for pid in "${client_pids[@]}"; do
        kill -TERM "$pid" 2>/dev/null
    done
    if ((${#pids[@]})); then
        for pid in "${pids[@]}"; do
            kill -TERM "$pid" 2>/dev/null
        done
        # Workers finish their task and the coordinator drains (--drain-seconds 5 below).
        for _ in $(seq 1 100); do
            local alive=0
            for pid in "${pids[@]}"; do
                kill -0 "$pid" 2>/dev/null && alive=1
            done
            ((alive)) || break
            sleep 0.1
        done
        for pid in "${pids[@]}"; do
            kill -KILL "$pid" 2>/dev/null
        done
    fi
    # Anything still running inside the namespaces this run created (it started all of it).
    for ns in "${namespaces[@]}"; do
        for pid in $(ip netns pids "$ns" 2>/dev/null); do
            kill -KILL "$pid" 2>/dev/null
        done
    done
    wait 2>/dev/null
    if [[ -n $keep_dir && -n $work && -d $work ]]; then
        mkdir -p "$keep_dir" && cp -r "$work/." "$keep_dir/" && log "kept logs and result in $keep_dir"
    fi
    if ((rc == 1)) && [[ -n $work && -d $work ]]; then
        local f
        for f in "$work"/*.log; do
            [[ -s $f ]] || continue
            log "---- last lines of $(basename "$f") ----"
            tail -n 25 "$f" >&2
        done
    fi
    # Deleting a namespace deletes its veth end, and with it the peer; "sw" holds the bridge.
    for ns in "${namespaces[@]}"; do
        ip netns del "$ns" 2>/dev/null || log "warning: could not delete namespace $ns"
    done
    [[ -n $work && -d $work ]] && rm -rf "$work"
    if ((rc == 0)); then
        log "cleaned up"
    else
        log "cleaned up after a failure (exit status $rc)"
    fi
    exit "$rc"
}
on_signal() {
    log "interrupted by SIG$1: cleaning up"
    exit $((128 + $2))
}
trap cleanup EXIT
trap 'on_signal INT 2' INT
trap 'on_signal TERM 15' TERM

work=$(mktemp -d "${TMPDIR:-/tmp}/scatterfarm-cluster.XXXXXX")
chmod 700 "$work"
export NO_COLOR=1 # plain logs in the log files

# The private network.
sw=$tag-sw
add_ns() {
    ip netns add "$1" || die "cannot create network namespace $1"
    namespaces+=("$1")
    ip -n "$1" link set lo up
}
# add_host NS ADDRESS PORT-NAME: a namespace with eth0 at ADDRESS/24, cabled to the bridge.
add_host() {
    add_ns "$1"
    ip -n "$sw" link add "$3" type veth peer name eth0 netns "$1"
    ip -n "$sw" link set "$3" master br0 up
    ip -n "$1" addr add "$2/24" dev eth0
    ip -n "$1" link set eth0 up
}

if ! ip netns add "$sw" 2>/dev/null; then
    log "SKIPPED: cannot create network namespaces here (ip netns add failed)"
    exit 77
fi
namespaces+=("$sw")
ip -n "$sw" link set lo up
ip -n "$sw" link add br0 type bridge
ip -n "$sw" link set br0 up

coord_ip=$subnet.1
client_ip=$subnet.100
add_host "$tag-coord" "$coord_ip" p-coord
add_host "$tag-client" "$client_ip" p-client
for i in $(seq 1 "$workers"); do
    add_host "$tag-w$i" "$subnet.$((10 + i))" "p-w$i"
done
log "network: bridge br0 in namespace $sw; coordinator $coord_ip, workers $subnet.11..$subnet.$((10 + workers)), client $client_ip"

# The shared token: the coordinator, every worker and the client read it from a file.
token=$work/token
(umask 077 && head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n' >"$token")
url=http://$coord_ip:7070

# client CMD ARGS...: a client command from the client namespace, bounded in time; runs in the
# background and is waited for, so that Ctrl-C reaches the trap at once.
client() {
    local rc=0
    SCATTERFARM_COORDINATOR=$url SCATTERFARM_TOKEN_FILE=$token \
        timeout -k 5 "$timeout_s" ip netns exec "$tag-client" "$binary" "$@" &
    client_pids+=($!)
    wait "$!" || rc=$?
    return "$rc"
}

log "starting the coordinator on $coord_ip:7070 (HTTP status on :8080)"
# `ip netns exec` execs the command: $! is the farm process itself (not a subshell), so that
# SIGTERM reaches it.
ip netns exec "$tag-coord" "$binary" coordinator \
    --listen "$coord_ip:7070" --http "$coord_ip:8080" \
    --data "$work/coordinator-data" --token-file "$token" \
    --task-seconds 0.25 --heartbeat-ms 500 --drain-seconds 5 \
    --address-file "$work/coordinator.url" \
    >"$work/coordinator.log" 2>&1 &
pids+=($!)
coord_pid=$!
for _ in $(seq 1 300); do
    [[ -s $work/coordinator.url ]] && break
    kill -0 "$coord_pid" 2>/dev/null || die "the coordinator exited at start"
    sleep 0.1
done
[[ -s $work/coordinator.url ]] || die "the coordinator did not listen within 30 s"
log "coordinator listening: $(cat "$work/coordinator.url")"

log "starting $workers worker(s) with --engine $engine"
for i in $(seq 1 "$workers"); do
    ip netns exec "$tag-w$i" "$binary" worker \
        --coordinator "$url" --token-file "$token" --engine "$engine" --name "host$i/$engine" \
        >"$work/worker$i.log" 2>&1 &
    pids+=($!)
done

# workers_json: the coordinator's worker listing.
workers_json() { client workers --json 2>>"$work/client.log"; }
# The name and tasks_completed of every worker in a listing, one "NAME COUNT" line each.
tasks_per_worker() {
    awk '
        /"name":/ { n = $0; sub(/^[^:]*: *"/, "", n); sub(/",?[[:space:]]*$/, "", n) }
        /"tasks_completed":/ { c = $0; sub(/^[^:]*: */, "", c); sub(/,?[[:space:]]*$/, "", c) }
        /^[[:space:]]*}/ { if (n != "") print n, c + 0; n = ""; c = "" }
    '
}

# Every worker must have registered before the job goes in, so that all of them get tasks.
deadline=$((SECONDS + 120))
while :; do
    registered=$(workers_json | grep -c '"worker_id"' || true)
    ((registered >= workers)) && break
    for pid in "${pids[@]}"; do
        kill -0 "$pid" 2>/dev/null || die "a farm process exited early"
    done
    ((SECONDS < deadline)) || die "only $registered of $workers workers registered within 120 s"
    sleep 0.5
done
log "all $workers workers registered"

if command -v curl >/dev/null; then
    # /metrics asks for the token, as Prometheus sends it.
    ip netns exec "$tag-client" curl -fsS --max-time 10 -H "Authorization: Bearer $(cat "$token")" \
        "http://$coord_ip:8080/metrics" >"$work/metrics.txt" ||
        die "the coordinator's HTTP /metrics did not answer"
    log "HTTP /metrics answered ($(wc -l <"$work/metrics.txt") lines)"
fi

# A job with a tiny budget.
cat >"$work/job.toml" <<'EOF'
# local-cluster.sh: a small reconstruction, just enough work for every worker.
scene = "demo8"
permutations = 1
iterations = 2
photons_per_iteration = 128
seed = 1
name = "local-cluster smoke test"
EOF
job=$(client submit "$work/job.toml" 2>>"$work/client.log") || die "submit failed"
[[ -n $job ]] || die "submit printed no job id"
log "submitted job $job; following it"
if [[ -t 2 ]]; then
    client watch "$job" || die "watch failed"
else
    client watch "$job" 2>>"$work/client.log" || die "watch failed (see client.log)"
fi

status=$(client status "$job" --json 2>>"$work/client.log") || die "status failed"
state=$(printf '%s\n' "$status" | sed -n 's/^ *"state": *"\([a-z]*\)".*/\1/p')
[[ $state == finished ]] || die "job $job ended in state '${state:-?}': $status"
log "job $job finished"

client result "$job" --out "$work/result" 2>>"$work/client.log" || die "result failed"
for f in report.json reconstruction.png materials.json; do
    [[ -s $work/result/$f ]] || die "the result has no $f"
done
log "result fetched: $(cd "$work/result" && printf '%s ' *)"

listing=$(workers_json) || die "workers --json failed"
per_worker=$(printf '%s\n' "$listing" | tasks_per_worker)
printf '%s\n' "$per_worker" | sed 's/^/[local-cluster]   tasks completed by /' >&2
for i in $(seq 1 "$workers"); do
    count=$(printf '%s\n' "$per_worker" | awk -v n="host$i/$engine" '$1 == n { print $2 }')
    [[ -n $count ]] || die "worker host$i is not in the coordinator's listing"
    ((count > 0)) || die "worker host$i completed no task"
done
log "every worker rendered part of the job"

# Stop as an operator would: SIGTERM to the workers (each finishes its task and leaves), then
# to the coordinator (it drains and stops). Each must exit 0.
log "stopping: SIGTERM to the workers, then to the coordinator"
for pid in "${pids[@]:1}"; do
    kill -TERM "$pid"
done
for i in $(seq 1 "$workers"); do
    rc=0
    wait "${pids[$i]}" || rc=$?
    ((rc == 0)) || die "worker host$i exited with status $rc after SIGTERM"
done
kill -TERM "$coord_pid"
rc=0
wait "$coord_pid" || rc=$?
((rc == 0)) || die "the coordinator exited with status $rc after SIGTERM"
pids=()
grep -q "coordinator stopped" "$work/coordinator.log" || die "the coordinator log does not say it stopped"
log "PASSED: $workers workers on their own hosts reconstructed job $job"
