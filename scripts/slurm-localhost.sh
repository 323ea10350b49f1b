#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, with accounting, for `make cluster-test`.
#
#   scripts/slurm-localhost.sh install  install what is missing (apt-get; exit 1 when it cannot)
#   scripts/slurm-localhost.sh up       install, configure, start, wait for an idle node
#   scripts/slurm-localhost.sh status   each daemon's PID, then sinfo (exit 3 when not all run)
#   scripts/slurm-localhost.sh down     cancel this cluster's jobs, stop every daemon `up` started, by PID,
#                                        remove the configuration `up` wrote
#
# Runs as root (Debian/Ubuntu: apt-get). Daemons run in the foreground (-D) in
# the background, no systemd: munged, mariadbd + slurmdbd (accounting, so that
# sacct answers as on a real cluster), slurmctld and slurmd. The node gets this
# machine's CPUs and memory as `slurmd -C` prints them. Configuration goes to
# the default paths (/etc/slurm/slurm.conf, slurmdbd.conf): a job step drops
# SLURM_CONF. It refuses to touch a slurm.conf it did not write. Without
# cgroups (containers): proctrack/linuxproc, task/none.
# State: $MOGAF_SLURM_STATE (PIDs, daemon output; default /run/mogaf-slurm) and
# /var/spool/mogaf-slurm (controller state: job ids go on across down/up).
set -euo pipefail

STATE=${MOGAF_SLURM_STATE:-/run/mogaf-slurm}
SPOOL=/var/spool/mogaf-slurm
CONF=/etc/slurm/slurm.conf
DBD_CONF=/etc/slurm/slurmdbd.conf
MARK="# written by mogaf scripts/slurm-localhost.sh (a one-node test cluster)"
CLUSTER=mogaf
PACKAGES=(slurmctld slurmd slurm-client munge slurmdbd mariadb-server)
DAEMONS=(munged mariadbd slurmdbd slurmctld slurmd) # start order; stopped in reverse
DB_SOCKET=/run/mysqld/mysqld.sock

say() { echo "slurm-localhost: $*"; }
die() {
    echo "slurm-localhost: error: $*" >&2
    exit 1
}

pid_of() { cat "$STATE/$1.pid" 2>/dev/null || true; }

# Alive and still the process we started (a PID can be reused).
alive() {
    local pid
    pid=$(pid_of "$1")
    [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null && [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = "$1" ]
}

start() { # name command...: runs it in the background, output to $STATE/name.log
    local name=$1
    shift
    "$@" >"$STATE/$name.log" 2>&1 &
    echo $! >"$STATE/$name.pid"
}

wait_for() { # seconds description command...
    local seconds=$1 what=$2
    shift 2
    local deadline=$((SECONDS + seconds))
    until "$@" >/dev/null 2>&1; do
        if [ $SECONDS -ge $deadline ]; then
            die "$what: not ready after ${seconds} s (logs in $STATE/)"
        fi
        sleep 0.5
    done
}

stop() {
    local name=$1 pid
    pid=$(pid_of "$name")
    if alive "$name"; then
        kill -TERM "$pid"
        for _ in $(seq 60); do
            kill -0 "$pid" 2>/dev/null || break
            sleep 0.25
        done
        if kill -0 "$pid" 2>/dev/null; then
            kill -KILL "$pid"
            say "$name (PID $pid) killed after 15 s"
        else
            say "$name (PID $pid) stopped"
        fi
    fi
    rm -f "$STATE/$name.pid"
}

install() {
    local missing=()
    for bin in munged mariadbd slurmdbd slurmctld slurmd sinfo sacct; do
        command -v "$bin" >/dev/null 2>&1 || missing+=("$bin")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    command -v apt-get >/dev/null 2>&1 || die "missing ${missing[*]} and no apt-get to install ${PACKAGES[*]}"
    say "installing ${PACKAGES[*]} (missing: ${missing[*]})"
    export DEBIAN_FRONTEND=noninteractive
    if ! apt-get install -y -q --no-install-recommends "${PACKAGES[@]}" >"$STATE/apt.log" 2>&1; then
        if ! { apt-get update -q && apt-get install -y -q --no-install-recommends "${PACKAGES[@]}"; } >>"$STATE/apt.log" 2>&1; then
            tail -n 5 "$STATE/apt.log" >&2
            die "apt-get install failed (all of it in $STATE/apt.log)"
        fi
    fi
}

ours_or_absent() { [ ! -e "$1" ] || [ "$(head -n1 "$1")" = "$MARK" ]; }

configure() {
    ours_or_absent "$CONF" || die "$CONF was not written by this script (a real SLURM installation?): not touching it"
    ours_or_absent "$DBD_CONF" || die "$DBD_CONF was not written by this script: not touching it"
    local node
    node=$(slurmd -C | head -n1) # NodeName=<host> CPUs=.. Boards=.. ... RealMemory=..
    [[ $node == NodeName=* ]] || die "slurmd -C printed no node line: $node"
    local host=${node%% *}
    host=${host#NodeName=}
    mkdir -p /etc/slurm "$SPOOL/ctld" "$SPOOL/slurmd" "$STATE/daemon"
    chown slurm:slurm "$SPOOL/ctld" "$STATE/daemon"
    cat >"$CONF" <<EOF
$MARK
ClusterName=$CLUSTER
SlurmctldHost=$host(127.0.0.1)
SlurmUser=slurm
AuthType=auth/munge
StateSaveLocation=$SPOOL/ctld
SlurmdSpoolDir=$SPOOL/slurmd
SlurmctldPidFile=$STATE/daemon/slurmctld.pid
SlurmdPidFile=$STATE/daemon/slurmd.pid
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
ReturnToService=2
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
MinJobAge=300
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
AccountingStoreFlags=job_comment
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=2
JobCompType=jobcomp/none
$node NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
    local pass
    pass=$(head -c 18 /dev/urandom | od -An -tx1 | tr -d ' \n')
    (
        umask 077
        cat >"$DBD_CONF" <<EOF
$MARK
AuthType=auth/munge
DbdHost=localhost
SlurmUser=slurm
PidFile=$STATE/daemon/slurmdbd.pid
StorageType=accounting_storage/mysql
StorageHost=localhost
StorageUser=slurm
StoragePass=$pass
StorageLoc=slurm_acct_db
EOF
    )
    chown slurm:slurm "$DBD_CONF"
    DB_PASS=$pass
}

up() {
    [ "$(id -u)" = 0 ] || die "run as root (installs packages, starts daemons)"
    mkdir -p "$STATE"
    local running=0
    for d in "${DAEMONS[@]}"; do alive "$d" && running=$((running + 1)); done
    if [ $running -eq ${#DAEMONS[@]} ]; then
        say "already up"
        status
        return 0
    fi
    [ $running -gt 0 ] && { say "partly up: restarting"; down; }
    install
    # shellcheck disable=SC2154 # rc is set in the trap itself
    trap 'rc=$?; [ $rc -eq 0 ] || { say "up failed: stopping what it started"; down; }' EXIT
    for d in "${DAEMONS[@]}"; do
        if pgrep -x "$d" >/dev/null; then
            die "a $d not started by this script runs (PID $(pgrep -x "$d" | head -n1)): stop it first (systemd: systemctl stop)"
        fi
    done
    configure

    # munge: authentication between the daemons and the commands
    if [ ! -s /etc/munge/munge.key ]; then
        mungekey --create --keyfile=/etc/munge/munge.key
        chown munge:munge /etc/munge/munge.key
        chmod 600 /etc/munge/munge.key
    fi
    mkdir -p /run/munge && chown munge:munge /run/munge
    start munged setpriv --reuid=munge --regid=munge --init-groups munged --foreground
    wait_for 20 munged sh -c 'munge -n | unmunge'

    # MariaDB (local socket only) for slurmdbd, the accounting sacct reads
    mkdir -p /run/mysqld && chown mysql:mysql /run/mysqld
    if [ ! -d /var/lib/mysql/mysql ]; then
        mariadb-install-db --user=mysql --datadir=/var/lib/mysql >"$STATE/mariadb-install.log" 2>&1
    fi
    start mariadbd mariadbd --user=mysql --datadir=/var/lib/mysql --socket="$DB_SOCKET" --skip-networking \
        --pid-file=/run/mysqld/mogaf-slurm.pid
    wait_for 60 mariadbd mariadb-admin --socket="$DB_SOCKET" ping
    mariadb --socket="$DB_SOCKET" -e "CREATE USER IF NOT EXISTS 'slurm'@'localhost';
        ALTER USER 'slurm'@'localhost' IDENTIFIED BY '$DB_PASS';
        GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost';"
    start slurmdbd slurmdbd -D
    wait_for 60 slurmdbd sacctmgr -n list cluster
    if [ -z "$(sacctmgr -n -P list cluster format=cluster where cluster=$CLUSTER)" ]; then
        sacctmgr -i add cluster "$CLUSTER" >/dev/null
    fi

    start slurmctld slurmctld -D
    wait_for 60 slurmctld scontrol ping
    start slurmd slurmd -D
    # shellcheck disable=SC2016 # expanded by that sh
    wait_for 60 "the node (idle)" sh -c '[ "$(sinfo -h -N -o %T | head -n1)" = idle ]'
    trap - EXIT
    say "up: $(sinfo -h -N -o '%N %c CPUs %m MB %T')"
}

down() {
    if alive slurmctld; then
        local jobs
        jobs=$(squeue -h -o %A 2>/dev/null | tr '\n' ' ' || true)
        if [ -n "$jobs" ]; then
            say "cancelling jobs $jobs"
            # shellcheck disable=SC2086 # one job id a word
            scancel $jobs || true
            sleep 2
        fi
    fi
    local i
    for ((i = ${#DAEMONS[@]} - 1; i >= 0; i--)); do stop "${DAEMONS[i]}"; done
    # `up` writes them again. Left behind with no controller running, a
    # slurm.conf makes every SLURM client command wait for it (MessageTimeout,
    # 10 s), and Snakemake's SLURM plugin runs `scontrol show config` as it
    # loads, so every later Snakemake start on this machine would wait too.
    local conf
    for conf in "$CONF" "$DBD_CONF"; do
        if [ -e "$conf" ] && ours_or_absent "$conf"; then rm -f "$conf"; fi
    done
}

status() {
    local all=0
    for d in "${DAEMONS[@]}"; do
        if alive "$d"; then
            say "$d running (PID $(pid_of "$d"))"
        else
            say "$d not running"
            all=3
        fi
    done
    if alive slurmctld; then sinfo -N -o '%N %c %m %T'; fi
    return $all
}

case "${1:-}" in
install)
    [ "$(id -u)" = 0 ] || die "run as root (apt-get)"
    mkdir -p "$STATE"
    install
    ;;
up) up ;;
down) down ;;
status) status ;;
*)
    echo "usage: $0 install|up|down|status" >&2
    exit 2
    ;;
esac
