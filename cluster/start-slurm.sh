#!/usr/bin/env bash
# A one-node SLURM cluster on this host, for running the workflow through the real scheduler
# (profiles/slurm). Debian/Ubuntu packages, as root:
#   apt-get install slurm-wlm slurmdbd munge mariadb-server
#   pip install -e ".[slurm]"
# Usage:
#   cluster/start-slurm.sh            # writes the configuration, starts the daemons
#   cluster/start-slurm.sh stop       # stops the daemons it started
#
# Daemons: munged (authentication), mariadbd + slurmdbd (accounting, so `sacct` lists every
# job), slurmctld (controller) and slurmd (this host as the only compute node, all its CPUs and
# memory in partition `main`). Everything - configuration, state, logs, the database - lives
# under EMA_UQ_SLURM_DIR (default: $TMPDIR or /tmp, subfolder ema-uq-slurm). The one change under
# /etc: /etc/slurm/slurm.conf becomes a link to the written configuration, because the Snakemake
# SLURM executor clears every SLURM_* variable (SLURM_CONF too) before it calls sbatch, so the
# jobs' srun reads the compiled-in default path; an existing slurm.conf that is not such a link
# is left alone and the script stops. Processes are tracked per job (proctrack/linuxproc), so the cluster runs in a
# container without cgroups.
set -euo pipefail

STATE="${EMA_UQ_SLURM_DIR:-${TMPDIR:-/tmp}/ema-uq-slurm}"
CONF="$STATE/etc/slurm.conf"
HOST="$(hostname -s)"
CLUSTER=ema-uq
ACCOUNT=ema-uq
USER_NAME="$(id -un)"
PORT_BASE="${EMA_UQ_SLURM_PORT:-6817}"      # slurmctld; slurmd +1, slurmdbd +2, mariadb +3

log() { echo "start-slurm: $*" >&2; }
pidfile_alive() { [[ -f "$1" ]] && kill -0 "$(cat "$1")" 2>/dev/null; }

stop() {
    for d in slurmd slurmctld slurmdbd; do
        if pidfile_alive "$STATE/run/$d.pid"; then kill "$(cat "$STATE/run/$d.pid")"; log "stopped $d"; fi
    done
    if pidfile_alive "$STATE/db/run/mariadb.pid"; then kill "$(cat "$STATE/db/run/mariadb.pid")"; log "stopped mariadb"; fi
    if pidfile_alive "$STATE/run/munged.pid"; then kill "$(cat "$STATE/run/munged.pid")"; log "stopped munged"; fi
}

if [[ "${1:-start}" == stop ]]; then stop; exit 0; fi
[[ "$(id -u)" == 0 ]] || { echo "start-slurm: error: run as root (the daemons switch to their own users)" >&2; exit 2; }
for exe in munged slurmctld slurmd slurmdbd mariadbd sbatch sacct; do
    command -v "$exe" >/dev/null || { echo "start-slurm: error: $exe not found; apt-get install slurm-wlm slurmdbd munge mariadb-server" >&2; exit 2; }
done

mkdir -p "$STATE"/{etc,run,log,spool/ctld,spool/d,munge,db/data,db/run}
chown -R slurm:slurm "$STATE/spool" "$STATE/log"
chmod 755 "$STATE" "$STATE/run" "$STATE/etc"

# --- munge --------------------------------------------------------------------------------
if ! pidfile_alive "$STATE/run/munged.pid"; then
    [[ -s /etc/munge/munge.key ]] || { mungekey --create 2>/dev/null || create-munge-key -f; }
    mkdir -p /run/munge && chown munge:munge /run/munge "$STATE/munge"
    sudo_munge() { su -s /bin/sh munge -c "$*"; }
    if command -v runuser >/dev/null; then
        runuser -u munge -- munged --pid-file="$STATE/munge/munged.pid" --log-file="$STATE/munge/munged.log" --force
    else
        sudo_munge munged --pid-file="$STATE/munge/munged.pid" --log-file="$STATE/munge/munged.log" --force
    fi
    sleep 1
    cp "$STATE/munge/munged.pid" "$STATE/run/munged.pid"
    log "munged started"
fi
munge -n | unmunge >/dev/null || { echo "start-slurm: error: munge does not authenticate; see $STATE/munge/munged.log" >&2; exit 2; }

# --- accounting database (mariadb) ----------------------------------------------------------
DB_PORT=$((PORT_BASE + 3))
DB_SOCK="$STATE/db/run/mariadb.sock"
if ! pidfile_alive "$STATE/db/run/mariadb.pid"; then
    chown -R mysql:mysql "$STATE/db"
    if [[ ! -d "$STATE/db/data/mysql" ]]; then
        mariadb-install-db --user=mysql --datadir="$STATE/db/data" --auth-root-authentication-method=socket >/dev/null
    fi
    mariadbd --no-defaults --user=mysql --datadir="$STATE/db/data" --socket="$DB_SOCK" --port="$DB_PORT" \
        --bind-address=127.0.0.1 --pid-file="$STATE/db/run/mariadb.pid" --log-error="$STATE/db/run/mariadb.log" \
        --innodb-buffer-pool-size=256M --innodb-lock-wait-timeout=900 >/dev/null 2>&1 &
    for _ in $(seq 60); do [[ -S "$DB_SOCK" ]] && break; sleep 1; done
    mariadb --socket="$DB_SOCK" -u root <<SQL
CREATE DATABASE IF NOT EXISTS slurm_acct_db;
CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY 'slurmdbd';
GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost';
FLUSH PRIVILEGES;
SQL
    log "mariadb started"
fi

# --- configuration ------------------------------------------------------------------------
read -r CPUS MEM < <(slurmd -C | awk '/NodeName/ {for (i=1;i<=NF;i++) {split($i,a,"="); v[a[1]]=a[2]}; print v["CPUs"], v["RealMemory"]}')
MEM=$((MEM * 9 / 10))   # leave some memory to the system
cat > "$CONF" <<CONF
# written by cluster/start-slurm.sh for host $HOST
ClusterName=$CLUSTER
SlurmctldHost=$HOST
SlurmctldPort=$PORT_BASE
SlurmdPort=$((PORT_BASE + 1))
SlurmUser=slurm
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/spool/ctld
SlurmdSpoolDir=$STATE/spool/d
SlurmctldPidFile=$STATE/run/slurmctld.pid
SlurmdPidFile=$STATE/run/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=30
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
MpiDefault=none
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
AccountingStoragePort=$((PORT_BASE + 2))
AccountingStorageEnforce=associations
AccountingStoreFlags=job_comment
JobCompType=jobcomp/filetxt
JobCompLoc=$STATE/log/jobcomp.txt
MinJobAge=300
NodeName=$HOST CPUs=$CPUS RealMemory=$MEM State=UNKNOWN
PartitionName=main Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
CONF
cat > "$STATE/etc/slurmdbd.conf" <<CONF
AuthType=auth/munge
DbdHost=localhost
DbdPort=$((PORT_BASE + 2))
SlurmUser=slurm
PidFile=$STATE/run/slurmdbd.pid
LogFile=$STATE/log/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=localhost
StoragePort=$DB_PORT
StorageLoc=slurm_acct_db
StorageUser=slurm
StoragePass=slurmdbd
CONF
chown slurm:slurm "$STATE/etc/slurmdbd.conf"
chmod 600 "$STATE/etc/slurmdbd.conf"
export SLURM_CONF="$CONF"
if [[ -e /etc/slurm/slurm.conf && ! -L /etc/slurm/slurm.conf ]]; then
    echo "start-slurm: error: /etc/slurm/slurm.conf exists and is not a link written here; move it away first" >&2
    exit 2
fi
mkdir -p /etc/slurm && ln -sfn "$CONF" /etc/slurm/slurm.conf

# --- daemons ------------------------------------------------------------------------------
if ! pidfile_alive "$STATE/run/slurmdbd.pid"; then
    # slurmdbd reaches mariadb over TCP on 127.0.0.1 ("localhost" would take the default socket)
    sed -i "s/^StorageHost=.*/StorageHost=127.0.0.1/" "$STATE/etc/slurmdbd.conf"
    SLURM_CONF="$CONF" slurmdbd          # reads slurmdbd.conf beside SLURM_CONF
    for _ in $(seq 30); do sacctmgr -i show cluster >/dev/null 2>&1 && break; sleep 1; done
    log "slurmdbd started"
fi
sacctmgr -i add cluster "$CLUSTER" >/dev/null 2>&1 || true
if ! pidfile_alive "$STATE/run/slurmctld.pid"; then
    slurmctld -f "$CONF"
    for _ in $(seq 30); do scontrol ping 2>/dev/null | grep -q UP && break; sleep 1; done
    log "slurmctld started"
fi
sacctmgr -i add account "$ACCOUNT" Cluster="$CLUSTER" Description=ema-uq Organization=ema-uq >/dev/null 2>&1 || true
sacctmgr -i add user "$USER_NAME" Account="$ACCOUNT" DefaultAccount="$ACCOUNT" >/dev/null 2>&1 || true
if ! pidfile_alive "$STATE/run/slurmd.pid"; then
    slurmd -f "$CONF"
    for _ in $(seq 30); do sinfo -h -o %T 2>/dev/null | grep -qv -e down -e unk && break; sleep 1; done
    log "slurmd started"
fi
scontrol update NodeName="$HOST" State=RESUME >/dev/null 2>&1 || true
sinfo >&2
echo "# /etc/slurm/slurm.conf -> $CONF; the SLURM commands need no SLURM_CONF"
