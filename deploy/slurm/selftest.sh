#!/usr/bin/env bash
# Tests scatterfarm-workers.sbatch without Slurm: the GPU-to-adapter mapping against a fake
# nvidia-smi, and the batch flow (srun, one worker per task, SIGTERM forwarding, exit status)
# against a fake srun that runs the tasks on this machine with the real scatterfarm binary.
#
#   deploy/slurm/selftest.sh [SCATTERFARM-BINARY]     (default target/release/scatterfarm; without
#                                                     a binary only the mapping is tested)
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
sbatch_script=$here/scatterfarm-workers.sbatch
binary=${1:-${SCATTERFARM_BIN:-$here/../../target/release/scatterfarm}}

tmp=$(mktemp -d "${TMPDIR:-/tmp}/scatterfarm-slurm-test.XXXXXX")
pids=()
cleanup() {
    local pid
    for pid in "${pids[@]}"; do
        kill -KILL "$pid" 2>/dev/null || true
    done
    rm -rf "$tmp"
}
trap cleanup EXIT

failures=0
passes=0
check() { # check NAME EXPECTED ACTUAL
    if [[ $2 == "$3" ]]; then
        passes=$((passes + 1))
        echo "ok   $1"
    else
        failures=$((failures + 1))
        echo "FAIL $1: expected '$2', got '$3'"
    fi
}

# A fake nvidia-smi: the rows of $FAKE_GPUS (index, uuid, bus id; ';'-separated).
mkdir -p "$tmp/nv" "$tmp/bin"
cat >"$tmp/nv/nvidia-smi" <<'EOF'
#!/usr/bin/env bash
IFS=';' read -r -a rows <<<"$FAKE_GPUS"
for r in "${rows[@]}"; do echo "$r"; done
EOF
chmod +x "$tmp/nv/nvidia-smi"
four='0, GPU-aaaa, 00000000:17:00.0;1, GPU-bbbb, 00000000:31:00.0;2, GPU-cccc, 00000000:B1:00.0;3, GPU-dddd, 00000000:CA:00.0'

# resolve ENV...: the adapter the sbatch script maps to, or "error".
resolve() {
    env -i PATH="$tmp/nv:/usr/bin:/bin" "$@" bash "$sbatch_script" --resolve-adapter 2>/dev/null || echo error
}
nonv() {
    env -i PATH="/usr/bin:/bin" "$@" bash "$sbatch_script" --resolve-adapter 2>/dev/null || echo error
}
check "bound task, unconstrained node: CUDA index -> PCI" 0000:b1:00.0 \
    "$(resolve FAKE_GPUS="$four" CUDA_VISIBLE_DEVICES=2 SLURM_LOCALID=2)"
check "bound task, cgroup shows one GPU: CUDA 0 -> its PCI" 0000:ca:00.0 \
    "$(resolve FAKE_GPUS='3, GPU-dddd, 00000000:CA:00.0' CUDA_VISIBLE_DEVICES=0 SLURM_LOCALID=1)"
check "unbound tasks: the SLURM_LOCALID-th GPU" 0000:ca:00.0 \
    "$(resolve FAKE_GPUS="$four" CUDA_VISIBLE_DEVICES=0,1,2,3 SLURM_LOCALID=3)"
check "UUID in CUDA_VISIBLE_DEVICES" 0000:31:00.0 \
    "$(resolve FAKE_GPUS="$four" CUDA_VISIBLE_DEVICES=GPU-bbbb SLURM_LOCALID=0)"
check "SLURM_STEP_GPUS holds node indices" 0000:ca:00.0 \
    "$(resolve FAKE_GPUS="$four" SLURM_STEP_GPUS=1,3 SLURM_LOCALID=1)"
check "no nvidia-smi: the index itself" 1 \
    "$(nonv CUDA_VISIBLE_DEVICES=1 SLURM_LOCALID=0)"
check "AMD: ROCR_VISIBLE_DEVICES" 2 \
    "$(nonv ROCR_VISIBLE_DEVICES=0,2 SLURM_LOCALID=1)"
check "SCATTERFARM_ADAPTER wins" "0000:65:00.0" \
    "$(resolve FAKE_GPUS="$four" CUDA_VISIBLE_DEVICES=2 SCATTERFARM_ADAPTER=0000:65:00.0)"
check "no GPU at all is an error" error "$(resolve FAKE_GPUS="$four" SLURM_LOCALID=0)"
check "more tasks than GPUs is an error" error \
    "$(resolve FAKE_GPUS="$four" CUDA_VISIBLE_DEVICES=0,1 SLURM_LOCALID=2)"

if [[ -x $binary ]]; then
    # A fake srun: runs --ntasks copies of `bash -c SCRIPT` here with SLURM_LOCALID set, relays
    # SIGUSR1 to them and, like the real one, kills them on SIGTERM and reports each task's exit
    # status. Each task runs in its own process group under a shell that only keeps its status
    # (like slurmstepd: no trap can interrupt its wait, and signals to the task leave it be).
    cat >"$tmp/bin/srun" <<'EOF'
#!/usr/bin/env bash
set -m
n=1
while [[ $1 == -* ]]; do
    case $1 in --ntasks=*) n=${1#--ntasks=} ;; esac
    shift
done
status=$(mktemp -d "${TMPDIR:-/tmp}/fake-srun.XXXXXX")
kids=()
for ((i = 0; i < n; i++)); do
    (
        trap '' TERM USR1
        r=0
        SLURM_LOCALID=$i SLURM_PROCID=$i "$@" || r=$?
        echo "$r" >"$status/$i.part" && mv "$status/$i.part" "$status/$i"
    ) &
    kids+=($!)
done
relay() { for k in "${kids[@]}"; do kill "-$1" -- "-$k" 2>/dev/null; done; }
trap 'relay USR1' USR1
trap 'relay KILL; exit 143' TERM
rc=0
for ((i = 0; i < n; i++)); do
    until [[ -e $status/$i ]]; do
        sleep 0.1
    done
    r=$(<"$status/$i")
    echo "srun: task $i: exited with status $r" >&2
    [[ $r == 0 ]] || rc=1
done
rm -rf "$status"
exit "$rc"
EOF
    chmod +x "$tmp/bin/srun"
    descendants() { # every process below $1
        local child
        for child in $(ps -o pid= --ppid "$1"); do
            echo "$child"
            descendants "$child"
        done
    }
    # flow NAME MODE: start the batch script with 2 CPU workers (no coordinator listens on
    # port 9: they measure their engine and retry connecting), then stop it as MODE says:
    #   batch: SIGTERM to the batch script alone (it forwards the request);
    #   all:   SIGTERM to every task process (`scancel --signal=TERM`, or --signal=TERM@120 at
    #          the time limit), then to the batch script: the forwarded SIGUSR1 must not
    #          count as a second SIGTERM (which would make a worker quit without its task).
    flow() {
        local name=$1 mode=$2 log=$tmp/flow-$2.log batch rc pid
        echo "flow ($name)"
        env PATH="$tmp/bin:$PATH" SLURM_NTASKS=2 SLURM_JOB_ID=42 SCATTERFARM_ENGINE=cpu \
            SCATTERFARM_BIN="$binary" SCATTERFARM_TOKEN=selftest NO_COLOR=1 \
            bash "$sbatch_script" http://127.0.0.1:9 >"$log" 2>&1 &
        batch=$!
        pids+=("$batch")
        for _ in $(seq 1 150); do
            [[ $(grep -c "cannot connect to the coordinator" "$log" || true) -ge 2 ]] && break
            sleep 0.2
        done
        if [[ $mode == all ]]; then
            # Slurm signals the step's processes (below srun), not srun, which is in the batch
            # step: SIGTERM to srun would make the real one SIGKILL its tasks.
            local srun_pid
            for srun_pid in $(ps -o pid= --ppid "$batch"); do
                for pid in $(descendants "$srun_pid"); do
                    kill -TERM "$pid" 2>/dev/null || true
                done
            done
        fi
        # (In mode all the batch script may be gone already: its workers stopped at once.)
        kill -TERM "$batch" 2>/dev/null || true
        rc=0
        for _ in $(seq 1 150); do
            kill -0 "$batch" 2>/dev/null || break
            sleep 0.2
        done
        if kill -0 "$batch" 2>/dev/null; then
            rc=timeout
        else
            wait "$batch" || rc=$?
        fi
        check "flow ($mode): the batch script exits 0" 0 "$rc"
        check "flow ($mode): both workers were asked to finish" 2 \
            "$(grep -c "shutting down: no more leases" "$log" || true)"
        check "flow ($mode): no worker quit on a second signal" 0 \
            "$(grep -c "second signal" "$log" || true)"
        check "flow ($mode): both workers exited 0" 2 \
            "$(grep -c "srun: task .: exited with status 0" "$log" || true)"
        check "flow ($mode): names carry node, job and task" 1 \
            "$(grep -c -- "--name .*/slurm-42-1" "$log" || true)"
        if ((failures)) || [[ -n ${SELFTEST_VERBOSE:-} ]]; then
            echo "---- $log ----"
            cat "$log"
        fi
    }
    flow "SIGTERM to the batch script alone: forwarded" batch
    flow "SIGTERM to every task process and the batch script: not doubled" all
else
    echo "skip flow test: no scatterfarm binary at $binary"
fi

echo "$passes passed, $failures failed"
((failures == 0))
