#!/usr/bin/env bash
# A SLURM cluster on this machine, for the test suite (tests/run/test_slurm_cluster.py) and for trying
# the generated batch scripts by hand: one node, or K nodes. Needs root (the daemons and the jobs run
# as root).
#
#   dir=$(slurm/testcluster.sh start)            # one node, localhost; prints the cluster's directory
#   dir=$(slurm/testcluster.sh start --nodes 2)  # two nodes, n1 and n2, once every node is idle
#   export SLURM_CONF=$dir/slurm.conf CAMPAIGN_TEST_SLURM=$dir/slurm.conf
#   sinfo; sbatch ...; squeue ...
#   slurm/testcluster.sh stop "$dir"             # stops exactly the daemons that start started
#
# Several nodes: one slurmd per node, each on its own port (NodeName=nK ... Port=P) and spool
# directory, each in its own UTS and mount namespaces (unshare): its hostname is nK, and its
# /etc/hosts (a bind mount visible only inside) is the machine's plus "127.0.0.1 n1 n2 ...", so
# that every node resolves every other. Jobs, their steps and MPI ranks inherit their node's
# namespaces: a job on two nodes runs on two hosts named n1 and n2, which talk over the loopback
# interface (no network namespace, no traffic off this machine). The namespaces end with the
# processes in them; nothing is mounted outside them.
#
# `start` installs Debian's packages when they are missing (apt-get update, then slurmctld, slurmd,
# slurm-client and munge), writes its own slurm.conf and munge key into a new temporary directory
# (state, spool, logs and pid files live there too), starts munged, slurmctld and slurmd without
# systemd, and waits until the node is idle. The configuration is SLURM as shipped where it matters
# to the scripts (MpiDefault=none) and needs no cgroups (proctrack/linuxproc, task/none). The node
# declares CPUS (default 4) CPUs whatever the machine has, so that 3-rank jobs run on 2 cores, and
# GPUS (default 2; 0 for none) GPUs as a generic resource with no GPU behind them, so that slurmctld
# accepts or refuses GPU jobs and sets CUDA_VISIBLE_DEVICES in them as on a GPU cluster.
# Only addresses on this machine are used (127.0.0.1, free ports chosen at start).
# `stop` signals the pids recorded by `start` (after checking that each still runs the daemon it was),
# waits for them to exit and removes the directory. Both commands are idempotent.
set -euo pipefail

CPUS=${CPUS:-4}
GPUS=${GPUS:-2}
NODES=1

die() { echo "testcluster: $*" >&2; exit 1; }
[[ "$GPUS" =~ ^[0-9]+$ ]] || die "GPUS must be a number of GPUs per node (0 for none), got '$GPUS'"

install_packages() {
    local missing=()
    command -v munged >/dev/null || missing+=(munge)
    command -v slurmctld >/dev/null || missing+=(slurmctld)
    command -v slurmd >/dev/null || missing+=(slurmd)
    command -v sbatch >/dev/null || missing+=(slurm-client)
    [ ${#missing[@]} -eq 0 ] && return 0
    [ "$(id -u)" -eq 0 ] || die "missing ${missing[*]}; install them (apt-get install ${missing[*]}) or run as root"
    echo "testcluster: installing ${missing[*]}" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >&2
    apt-get install -y -qq --no-install-recommends munge slurmctld slurmd slurm-client >&2
}

free_port() {
    python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

# Does the pid recorded in the file $1 still run the daemon $2 of the cluster in directory $3
# (its name, and the directory on its command line)?
alive() {
    local pid
    [ -s "$1" ] || return 1
    pid=$(cat "$1" 2>/dev/null)
    [ -n "$pid" ] && [ -r "/proc/$pid/comm" ] && [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = "$2" ] &&
        tr '\0' ' ' < "/proc/$pid/cmdline" 2>/dev/null | grep -qF -- "$3/"
}

stop_daemon() {  # pid file, daemon name, cluster directory
    local pid i
    alive "$1" "$2" "$3" || return 0
    pid=$(cat "$1")
    kill -TERM "$pid" 2>/dev/null || true
    for i in $(seq 100); do alive "$1" "$2" "$3" || break; sleep 0.1; done
    if alive "$1" "$2" "$3"; then kill -KILL "$pid" 2>/dev/null || true; fi
}

stop() {
    local dir=$1 pidfile
    [ -d "$dir" ] || return 0
    [ -f "$dir/testcluster" ] || die "$dir was not made by testcluster.sh start; not touching it"
    for pidfile in "$dir"/run/slurmd-*.pid; do
        [ -e "$pidfile" ] && stop_daemon "$pidfile" slurmd "$dir"
    done
    stop_daemon "$dir/run/slurmctld.pid" slurmctld "$dir"
    stop_daemon "$dir/run/munged.pid" munged "$dir"
    rm -rf "$dir"
}

# Start the slurmd of node $2 (cluster directory $1): on one node as it is, on several in its own
# UTS and mount namespaces, with hostname $2 and the cluster's hosts file.
start_slurmd() {
    local dir=$1 node=$2
    mkdir -p "$dir/spool/$node"
    if [ "$NODES" -eq 1 ]; then
        slurmd -f "$dir/slurm.conf" -N "$node"
    else
        unshare --uts --mount --propagation slave \
            sh -c 'mount --bind "$1/hosts" /etc/hosts && hostname "$2" && exec slurmd -f "$1/slurm.conf" -N "$2"' \
            sh "$dir" "$node"
    fi
}

start() {
    install_packages
    [ "$(id -u)" -eq 0 ] || die "the test cluster runs its daemons and jobs as root; run it as root"
    local dir ctld_port slurmd_port i k port nodes_line names state first_job gres gres_types
    dir=$(mktemp -d "${TMPDIR:-/tmp}/campaign-slurm.XXXXXX")
    touch "$dir/testcluster"
    trap 'echo "testcluster: start failed; logs follow" >&2; tail -n 30 "$dir"/log/* >&2 || true; stop "$dir"' ERR
    mkdir -p "$dir/run" "$dir/log" "$dir/state" "$dir/spool" "$dir/munge"
    chmod 700 "$dir/munge"
    head -c 1024 /dev/urandom > "$dir/munge/munge.key"
    chmod 400 "$dir/munge/munge.key"
    munged --force --socket="$dir/munge/munge.socket" --key-file="$dir/munge/munge.key" \
        --pid-file="$dir/run/munged.pid" --log-file="$dir/log/munged.log" --seed-file="$dir/munge/munged.seed"
    for i in $(seq 50); do [ -S "$dir/munge/munge.socket" ] && break; sleep 0.1; done
    munge -n --socket="$dir/munge/munge.socket" | unmunge --socket="$dir/munge/munge.socket" >/dev/null

    # GPUs as a generic resource: GPUS per node, no GPU behind them (docs/CLUSTERS.md#gpu-jobs). SLURM
    # 22.05 drops a gpu GRES without File= ("Removing file-less GPU"), and without a character device
    # sets no CUDA_VISIBLE_DEVICES: each "GPU" is a device node in the cluster's directory with
    # /dev/null's numbers (a regular file, where mknod is not allowed: counted, no CUDA_VISIBLE_DEVICES).
    gres="" gres_types=""
    if [ "$GPUS" -gt 0 ]; then
        gres=" Gres=gpu:$GPUS" gres_types="GresTypes=gpu"
        mkdir -p "$dir/dev"
        for i in $(seq 0 $((GPUS - 1))); do
            mknod "$dir/dev/gpu$i" c 1 3 2>/dev/null || : > "$dir/dev/gpu$i"
        done
        echo "Name=gpu Count=$GPUS File=$dir/dev/gpu[0-$((GPUS - 1))]" > "$dir/gres.conf"
    fi
    ctld_port=$(free_port)
    slurmd_port=$(free_port)
    while [ "$slurmd_port" = "$ctld_port" ]; do slurmd_port=$(free_port); done
    if [ "$NODES" -eq 1 ]; then
        names=localhost
        nodes_line="NodeName=localhost NodeHostname=localhost NodeAddr=127.0.0.1 CPUs=$CPUS RealMemory=1000$gres State=UNKNOWN"
    else
        names=$(seq -s, -f 'n%g' 1 "$NODES")
        nodes_line=""
        for k in $(seq "$NODES"); do
            port=$(free_port)
            while [ "$port" = "$ctld_port" ] || echo "$nodes_line" | grep -q "Port=$port "; do port=$(free_port); done
            nodes_line+="NodeName=n$k NodeHostname=n$k NodeAddr=127.0.0.1 Port=$port CPUs=$CPUS RealMemory=1000$gres State=UNKNOWN"$'\n'
        done
        { cat /etc/hosts; echo "127.0.0.1 $(echo "$names" | tr , ' ')  # testcluster nodes"; } > "$dir/hosts"
    fi
    # Job ids start at a random number: a rank killed by SIGKILL leaves MPICH's shared-memory segment
    # in /dev/shm, named after the host and the job step, and a later cluster's job of the same id on
    # the same host would attach to it and hang in MPI_Init.
    first_job=$(( (RANDOM * 32768 + RANDOM) % 60000000 + 1 ))
    cat > "$dir/slurm.conf" <<EOF
# written by slurm/testcluster.sh
ClusterName=campaigntest
FirstJobId=$first_job
SlurmctldHost=localhost(127.0.0.1)
SlurmctldPort=$ctld_port
SlurmdPort=$slurmd_port
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$dir/munge/munge.socket
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool/%n
SlurmctldPidFile=$dir/run/slurmctld.pid
SlurmdPidFile=$dir/run/slurmd-%n.pid
SlurmctldLogFile=$dir/log/slurmctld.log
SlurmdLogFile=$dir/log/slurmd-%n.log
SlurmctldDebug=info
SlurmdDebug=info
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SchedulerType=sched/backfill
SchedulerParameters=sched_min_interval=100000
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SlurmdParameters=config_overrides
ReturnToService=2
MinJobAge=600
KillWait=10
InactiveLimit=0
MailProg=/bin/true
$gres_types
$nodes_line
PartitionName=debug Nodes=$names Default=YES MaxTime=INFINITE State=UP
EOF
    export SLURM_CONF=$dir/slurm.conf
    slurmctld -f "$dir/slurm.conf"
    for i in $(seq 100); do scontrol ping >/dev/null 2>&1 && break; sleep 0.1; done
    for node in ${names//,/ }; do start_slurmd "$dir" "$node"; done
    for i in $(seq 300); do
        state=$(sinfo -h -N -o %T 2>/dev/null | sort -u | tr '\n' ' ')
        [ "$state" = "idle " ] && [ "$(sinfo -h -N -o %N | wc -l)" -eq "$NODES" ] && break
        sleep 0.1
    done
    [ "$state" = "idle " ] || { echo "testcluster: the nodes did not become idle: $(sinfo -N)" >&2; false; }
    alive "$dir/run/slurmctld.pid" slurmctld "$dir" && alive "$dir/run/munged.pid" munged "$dir"
    for node in ${names//,/ }; do alive "$dir/run/slurmd-$node.pid" slurmd "$dir"; done
    trap - ERR
    echo "$dir"
}

case "${1:-}" in
    start)
        if [ "${2:-}" = "--nodes" ]; then
            NODES=${3:-}
            [[ "$NODES" =~ ^[1-9][0-9]?$ ]] || die "--nodes needs a number of nodes (1-99), got '${3:-}'"
        elif [ $# -gt 1 ]; then
            die "usage: $0 start [--nodes K]"
        fi
        start ;;
    stop) [ $# -eq 2 ] || die "usage: $0 stop DIR"; stop "$2" ;;
    *) die "usage: $0 start [--nodes K] | $0 stop DIR" ;;
esac
