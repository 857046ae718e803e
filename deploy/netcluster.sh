#!/usr/bin/env bash
# An N-node Ray cluster on one Linux host, with a shaped network link per node.
#
#   bash deploy/netcluster.sh up N --bandwidth 1gbit [--delay 0.1ms] [--cpus-per-node X]
#   bash deploy/netcluster.sh shape --bandwidth 100mbit [--delay 0ms]   # re-shape, Ray stays up
#   bash deploy/netcluster.sh status | address | raylet-pid I
#   bash deploy/netcluster.sh exec I -- COMMAND...                     # run inside node I
#   bash deploy/netcluster.sh down
#
# Node i (0 <= i < N) is a network namespace <name>-ns<i> holding its own raylet and object
# store, so Ray objects between nodes really cross links. Each namespace has a veth pair to
# a bridge <name>-br. Each link is shaped in both directions (htb at the bandwidth, netem
# for the delay): traffic between two nodes crosses both of their links, like hosts on one
# switch. Each node gets a CPU share: a cgroup CPU quota of --cpus-per-node (default: the
# host's cores / N) where cgroups are writable; with --pin (or without writable cgroups)
# also its own cores through taskset, when there are enough. Pinning is off by default: on a
# host shared with other work, a pinned node cannot move to an idle core.
#
# The head (GCS and a raylet with no CPUs, so no shard runs there) lives in the root
# namespace on the bridge's address: a Ray driver must run beside a raylet whose address it
# can serve on, so a driver in the root namespace (the `nprt` command, a test, a benchmark)
# joins with `--ray-address $(bash deploy/netcluster.sh address)` and RAY_AUTH_MODE=token.
# The head is the coordinator's machine; its traffic to node i crosses node i's link.
#
# `down` kills only the processes `up` started (each node's session, and everything inside
# the namespaces; never `ray stop`, which would stop every Ray on the host) and removes every
# namespace, link, cgroup and file that `up` made; a failed `up` does the same before exiting.
#
# Options: --name NAME (prefix, <= 6 characters; default nprt), --subnet A.B.C (default
# 10.213.0), --port P (the GCS port; P+1 to P+3 go to the head's client server, agent and
# dashboard; default 26379), --object-store-mb M (per node, default 256), --auth
# token|disabled (Ray's token authentication; default token, from ~/.ray/auth_token),
# --pin (taskset each node to its own cores as well as the quota), --python PATH (the Ray
# binary is the one next to it; default $PYTHON, $VENV/bin/python, the checkout's .venv,
# python3). Needs root, iproute2 (installed with apt-get when missing) and network
# namespaces; exit status 3 means network namespaces are not available here.
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
NAME=nprt
SUBNET=10.213.0
BANDWIDTH=1gbit
DELAY=0ms
CPUS=""
STORE_MB=256
PY=${PYTHON:-}
GCS_PORT=26379
AUTH=token
PIN=0

die() { echo "netcluster: $*" >&2; exit 1; }
say() { echo "netcluster: $*" >&2; }

usage() {  # the comment block above
  awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "${BASH_SOURCE[0]}"
  exit "${1:-2}"
}

parse_opts() {
  while [ $# -gt 0 ]; do
    case "$1" in
      --bandwidth) BANDWIDTH=$2; shift 2 ;;
      --delay) DELAY=$2; shift 2 ;;
      --cpus-per-node) CPUS=$2; shift 2 ;;
      --name) NAME=$2; shift 2 ;;
      --subnet) SUBNET=$2; shift 2 ;;
      --object-store-mb) STORE_MB=$2; shift 2 ;;
      --python) PY=$2; shift 2 ;;
      --pin) PIN=1; shift ;;
      --port) GCS_PORT=$2; shift 2 ;;
      --auth) AUTH=$2; shift 2 ;;
      -h|--help) usage 0 ;;
      *) die "unknown option $1 (see --help)" ;;
    esac
  done
  [ "${#NAME}" -le 6 ] || die "--name $NAME: at most 6 characters (interface names are short)"
  [[ "$BANDWIDTH" =~ ^[0-9.]+(bit|kbit|mbit|gbit)$ ]] || \
    die "--bandwidth $BANDWIDTH: expected a number and bit, kbit, mbit or gbit (e.g. 1gbit)"
  [[ "$DELAY" =~ ^[0-9.]+(us|ms|s)$ ]] || die "--delay $DELAY: expected e.g. 0.1ms"
  [[ "$GCS_PORT" =~ ^[0-9]+$ ]] || die "--port $GCS_PORT: expected a port number"
  [[ "$AUTH" =~ ^(token|disabled)$ ]] || die "--auth $AUTH: token or disabled"
  [[ "$SUBNET" =~ ^[0-9]+\.[0-9]+\.[0-9]+$ ]] || die "--subnet $SUBNET: expected A.B.C"
}

state_dir() { echo "${NPRT_NETCLUSTER_DIR:-/tmp/nprt-netcluster-$NAME}"; }
ns() { echo "$NAME-ns$1"; }
host_if() { echo "$NAME-v$1"; }
bridge() { echo "$NAME-br"; }
node_ip() { echo "$SUBNET.$((10 + $1))"; }

find_python() {
  if [ -z "$PY" ]; then
    if [ -n "${VENV:-}" ]; then PY=$VENV/bin/python
    elif [ -x "$REPO/.venv/bin/python" ]; then PY=$REPO/.venv/bin/python
    else PY=$(command -v python3 || true)
    fi
  fi
  [ -x "$PY" ] || die "no python at '$PY' (give --python PATH or PYTHON=...)"
  RAY=$(dirname "$PY")/ray
  [ -x "$RAY" ] || die "no ray next to $PY (expected $RAY; install the package in that venv)"
}

need_tools() {
  [ "$(id -u)" = 0 ] || die "needs root (network namespaces, veth links and tc)"
  if ! command -v ip >/dev/null || ! command -v tc >/dev/null; then
    command -v apt-get >/dev/null || die "needs iproute2 (ip, tc) and there is no apt-get"
    say "installing iproute2 with apt-get"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq iproute2 >/dev/null
  fi
  command -v taskset >/dev/null || say "no taskset: nodes share every core"
}

check_netns() {
  local probe="$NAME-probe$$" err
  if ! err=$(ip netns add "$probe" 2>&1); then
    echo "netcluster: network namespaces are not available here: $err" >&2
    echo "netcluster: (a container needs CAP_SYS_ADMIN and CAP_NET_ADMIN, e.g." \
         "docker run --privileged)" >&2
    exit 3
  fi
  ip netns del "$probe"
}

# -- CPU shares -------------------------------------------------------------------------

CG_V1=/sys/fs/cgroup/cpu
cgroup_dir() {  # the parent cgroup for this cluster, or nothing when cgroups are read-only
  if [ -f /sys/fs/cgroup/cgroup.controllers ]; then
    grep -qw cpu /sys/fs/cgroup/cgroup.controllers && [ -w /sys/fs/cgroup ] && \
      echo "/sys/fs/cgroup/$NAME-netcluster"
  elif [ -d "$CG_V1" ] && [ -w "$CG_V1" ]; then
    echo "$CG_V1/$NAME-netcluster"
  fi
  return 0
}

make_cgroup() {  # make_cgroup I CPUS -> prints the node's cgroup dir, or nothing
  local parent quota
  parent=$(cgroup_dir)
  [ -n "$parent" ] || return 0
  quota=$(awk -v c="$2" 'BEGIN { printf "%d", c * 100000 }')
  if [ -f /sys/fs/cgroup/cgroup.controllers ]; then
    mkdir -p "$parent"
    echo +cpu > "$parent/cgroup.subtree_control" 2>/dev/null || true
    mkdir -p "$parent/node$1"
    echo "$quota 100000" > "$parent/node$1/cpu.max"
  else
    mkdir -p "$parent/node$1"
    echo 100000 > "$parent/node$1/cpu.cfs_period_us"
    echo "$quota" > "$parent/node$1/cpu.cfs_quota_us"
  fi
  echo "$parent/node$1"
}

cores_of() {  # cores_of I N CPUS -> a taskset list when every node can have its own cores
  local ncores per
  ncores=$(nproc)
  per=$(awk -v c="$3" 'BEGIN { p = int(c); if (p < c) p++; if (p < 1) p = 1; print p }')
  if [ $(($2 * per)) -le "$ncores" ] && command -v taskset >/dev/null; then
    echo "$(($1 * per))-$(($1 * per + per - 1))"
  fi
}

# -- links --------------------------------------------------------------------------------

shape_dev() {  # shape_dev "ip netns exec NS" DEV : htb at BANDWIDTH, then netem for DELAY
  local run=$1 dev=$2 burst
  # One 4 ms tick's worth of bytes (at least 64 KiB, one GSO packet), so htb can keep up
  # at high rates without letting more than that through at once.
  burst=$(awk -v b="$BANDWIDTH" 'BEGIN {
    n = b + 0; u = b; sub(/^[0-9.]+/, "", u)
    m = (u == "gbit") ? 1e9 : (u == "mbit") ? 1e6 : (u == "kbit") ? 1e3 : 1
    x = n * m / 8 / 250; if (x < 65536) x = 65536; printf "%d", x }')
  $run tc qdisc show dev "$dev" | grep "qdisc htb 1: root" >/dev/null || \
    $run tc qdisc replace dev "$dev" root handle 1: htb default 10
  $run tc class replace dev "$dev" parent 1: classid 1:10 htb rate "$BANDWIDTH" \
    ceil "$BANDWIDTH" burst "$burst" cburst "$burst" quantum 65536
  # The leaf is deleted and added again: tc cannot change one qdisc kind into another.
  $run tc qdisc del dev "$dev" parent 1:10 2>/dev/null || true
  if has_delay; then
    $run tc qdisc add dev "$dev" parent 1:10 handle 10: netem delay "$DELAY" limit 100000
  else
    $run tc qdisc add dev "$dev" parent 1:10 handle 10: pfifo limit 100000
  fi
}

has_delay() { [ "$(awk -v d="$DELAY" 'BEGIN { print (d + 0 > 0) }')" = 1 ]; }

check_netem() {  # before touching any link: a delay needs the kernel's netem
  has_delay || return 0
  local probe="$NAME-probe$$" ok=0
  ip netns add "$probe"
  ip netns exec "$probe" tc qdisc add dev lo root netem delay "$DELAY" 2>/dev/null && ok=1
  ip netns del "$probe"
  [ "$ok" = 1 ] || die "cannot give links a $DELAY delay: this kernel has no netem" \
    "(sch_netem); use --delay 0ms"
}

shape_node() {  # both directions of node I's link
  shape_dev "ip netns exec $(ns "$1")" eth0  # node -> switch
  shape_dev "" "$(host_if "$1")"             # switch -> node
}

make_node() {  # namespace, veth pair to the bridge, address, shaping
  local i=$1 n
  n=$(ns "$i")
  ip netns add "$n"
  ip link add "$(host_if "$i")" type veth peer name "$NAME-p$i"
  ip link set "$NAME-p$i" netns "$n"
  ip -n "$n" link set "$NAME-p$i" name eth0
  ip -n "$n" addr add "$(node_ip "$i")/24" dev eth0
  ip -n "$n" link set lo up
  ip -n "$n" link set eth0 up
  ip link set "$(host_if "$i")" master "$(bridge)"
  ip link set "$(host_if "$i")" up
  shape_node "$i"
}

# -- Ray ----------------------------------------------------------------------------------

launch() {  # launch TAG CGROUP COMMAND... : in a new session (recorded, for down) and cgroup
  # The cgroup is joined before entering a namespace (there /sys is remounted without
  # cgroups), so raylet, object store and workers all run in it.
  CG="$2" SID_FILE="$STATE/sid-$1" RAY_USAGE_STATS_ENABLED=0 setsid -w bash -c '
    echo $$ > "$SID_FILE"; [ -z "$CG" ] || echo $$ > "$CG/cgroup.procs"; exec "$@"' \
    "launch-$1" "${@:3}" > "$STATE/ray-start-$1.log" 2>&1 || {
      cat "$STATE/ray-start-$1.log" >&2; die "ray start failed for $1"; }
}

port_free() {
  [ -z "$(ss -Hltn "sport = :$1" 2>/dev/null)" ] || die "port $1 is in use (give --port)"
}

start_head() {  # GCS and a CPU-less raylet in the root namespace, on the bridge address
  local p
  for p in "$GCS_PORT" $((GCS_PORT + 1)) $((GCS_PORT + 2)) $((GCS_PORT + 3)); do port_free "$p"; done
  say "head: root namespace $SUBNET.1:$GCS_PORT (GCS, no CPUs: the coordinator's node)"
  launch head "" "$RAY" start --head --node-ip-address="$SUBNET.1" --port="$GCS_PORT" \
    --ray-client-server-port=$((GCS_PORT + 1)) --dashboard-agent-listen-port=$((GCS_PORT + 2)) \
    --dashboard-port=$((GCS_PORT + 3)) \
    --num-cpus=0 --object-store-memory=$((STORE_MB * 1024 * 1024)) --include-dashboard=false \
    --disable-usage-stats --temp-dir="$STATE/ray" --resources='{"netcluster_head": 1}' \
    --system-config='{"max_direct_call_object_size":1048576}'  # nprt's (raysession.py)
}

start_node() {  # start_node I : a raylet and object store inside namespace I
  local i=$1 cg cores pin=()
  cg=$(make_cgroup "$i" "$CPUS")
  cores=""
  [ "$PIN" = 1 ] || [ -z "$cg" ] && cores=$(cores_of "$i" "$N" "$CPUS")
  [ -n "$cores" ] && pin=(taskset -c "$cores")
  say "node $i: $(ns "$i") $(node_ip "$i"), ${cores:+cores $cores, }${cg:+quota $CPUS CPU, }$NUM_CPUS Ray CPUs"
  launch "$i" "$cg" ip netns exec "$(ns "$i")" "${pin[@]}" "$RAY" start \
    --address="$SUBNET.1:$GCS_PORT" --node-ip-address="$(node_ip "$i")" \
    --num-cpus="$NUM_CPUS" --object-store-memory=$((STORE_MB * 1024 * 1024)) \
    --disable-usage-stats --resources="{\"netnode$i\": 1}"
}

wait_nodes() {  # until the GCS lists every node alive
  "$PY" - "$SUBNET.1:$GCS_PORT" $((N + 1)) <<'EOF'
import sys, time
from ray._raylet import GcsClient
client = GcsClient(address=sys.argv[1])
want, deadline, alive = int(sys.argv[2]), time.time() + 120, []
while time.time() < deadline:
    alive = [n for n in client.get_all_node_info().values() if n.state == 0]
    if len(alive) >= want:
        sys.exit(0)
    time.sleep(0.5)
sys.exit(f"only {len(alive)} of {want} Ray nodes came up within 120 s")
EOF
}

# -- commands ------------------------------------------------------------------------------

cmd_up() {
  [ $# -ge 1 ] && [[ "$1" =~ ^[0-9]+$ ]] && [ "$1" -ge 1 ] || die "up N: N nodes (N >= 1)"
  N=$1; shift
  parse_opts "$@"
  STATE=$(state_dir)
  need_tools
  [ -e "$STATE" ] && die "a cluster named $NAME is up already ($STATE); run down first"
  ip link show "$(bridge)" >/dev/null 2>&1 && \
    die "a bridge $(bridge) exists already: another cluster named $NAME? (give --name)"
  check_netns
  check_netem
  find_python
  [ -n "$CPUS" ] || CPUS=$(awk -v c="$(nproc)" -v n="$N" 'BEGIN { printf "%g", c / n }')
  NUM_CPUS=$(awk -v c="$CPUS" 'BEGIN { p = int(c + 0.5); print (p < 1) ? 1 : p }')
  export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"  # workers import this checkout
  # Every node and every driver on this host reads the token from ~/.ray/auth_token.
  export RAY_AUTH_MODE=$AUTH
  if [ "$AUTH" = token ] && [ -z "${RAY_AUTH_TOKEN:-}${RAY_AUTH_TOKEN_PATH:-}" ]; then
    "$RAY" get-auth-token --generate >/dev/null
  fi
  UP_DONE=0
  trap 'up_failed' EXIT
  trap 'exit 130' INT TERM
  mkdir -p "$STATE"
  printf 'N=%s\nNAME=%s\nSUBNET=%s\n' "$N" "$NAME" "$SUBNET" > "$STATE/env"
  ip link add "$(bridge)" type bridge
  ip addr add "$SUBNET.1/24" dev "$(bridge)"
  ip link set "$(bridge)" up
  for ((i = 0; i < N; i++)); do make_node "$i"; done
  echo "$BANDWIDTH $DELAY" > "$STATE/shape"
  start_head
  for ((i = 0; i < N; i++)); do start_node "$i"; done
  wait_nodes
  echo "$SUBNET.1:$GCS_PORT" > "$STATE/address"
  UP_DONE=1
  trap - EXIT INT TERM
  say "$N nodes up, links $BANDWIDTH delay $DELAY; Ray logs in $STATE/ray/session_latest/logs"
  say "drivers: RAY_AUTH_MODE=$AUTH nprt render ... --ray-address $(cat "$STATE/address")"
  cat "$STATE/address"
}

up_failed() {
  [ "${UP_DONE:-1}" = 1 ] && return 0
  say "up failed; removing what it made"
  cmd_down >/dev/null 2>&1 || true
}

load_state() {
  parse_opts "$@"
  STATE=$(state_dir)
  [ -f "$STATE/env" ] || die "no cluster named $NAME is up ($STATE/env missing)"
  # shellcheck disable=SC1091
  . "$STATE/env"
}

cmd_shape() {
  load_state "$@"
  check_netem
  for ((i = 0; i < N; i++)); do shape_node "$i"; done
  echo "$BANDWIDTH $DELAY" > "$STATE/shape"
  say "$N links now $BANDWIDTH delay $DELAY"
}

cmd_status() {
  load_state "$@"
  echo "address $(cat "$STATE/address" 2>/dev/null || echo '(not up)')"
  echo "links $(cat "$STATE/shape")"
  for ((i = 0; i < N; i++)); do
    echo "node $i $(ns "$i") $(node_ip "$i") processes $(ip netns pids "$(ns "$i")" | wc -l)"
  done
}

cmd_raylet_pid() {  # raylet-pid I: the raylet process of node I
  local i=${1:?raylet-pid I}; shift
  load_state "$@"
  local pid
  for pid in $(ip netns pids "$(ns "$i")"); do
    if [ "$(cat "/proc/$pid/comm" 2>/dev/null)" = raylet ]; then echo "$pid"; return 0; fi
  done
  die "no raylet in $(ns "$i")"
}

cmd_exec() {  # exec I [--name NAME] -- COMMAND...
  local i=${1:?exec I -- COMMAND}; shift
  while [ $# -gt 0 ] && [ "$1" != -- ]; do
    case "$1" in --name) NAME=$2; shift 2 ;; *) die "exec I [--name NAME] -- COMMAND" ;; esac
  done
  [ "${1:-}" = -- ] && shift
  [ $# -gt 0 ] || die "exec I -- COMMAND: no command"
  ip netns list | grep -E "^$(ns "$i")( |$)" >/dev/null || die "no namespace $(ns "$i")"
  exec ip netns exec "$(ns "$i")" "$@"
}

kill_ns_procs() {  # TERM, then KILL what is left, of every process in namespace $1
  local n=$1 pids try
  for try in 1 2 3 4 5 6 7 8 9 10 11; do
    pids=$(ip netns pids "$n" 2>/dev/null || true)
    [ -z "$pids" ] && return 0
    if [ "$try" = 1 ]; then kill -TERM $pids 2>/dev/null || true
    elif [ "$try" -ge 6 ]; then kill -KILL $pids 2>/dev/null || true
    fi
    sleep 0.5
  done
  say "processes still in $n: $pids"
}

cmd_down() {
  [ -n "${STATE:-}" ] || { parse_opts "$@"; STATE=$(state_dir); }
  [ -f "$STATE/env" ] && . "$STATE/env"
  local n i cg sid left
  for sig in TERM KILL; do  # every process of every session up started (head included)
    for i in "$STATE"/sid-*; do
      [ -f "$i" ] || continue
      sid=$(cat "$i")
      for n in $(session_pids "$sid"); do kill -"$sig" "$n" 2>/dev/null || true; done
    done
    if [ "$sig" = TERM ]; then sleep 1; fi
  done
  for n in $(ip netns list 2>/dev/null | awk '{print $1}' | grep -E "^$NAME-ns[0-9]+$" || true); do
    kill_ns_procs "$n"
  done
  for n in $(ip netns list 2>/dev/null | awk '{print $1}' | grep -E "^$NAME-ns[0-9]+$" || true); do
    ip netns del "$n"
  done
  # veth ends left in the root namespace (their peers went with the namespaces), the bridge
  for i in $(ip -o link show 2>/dev/null | awk -F': ' '{print $2}' | sed 's/@.*//' \
             | grep -E "^($NAME-v[0-9]+|$NAME-p[0-9]+|$NAME-br)$" || true); do
    ip link del "$i" 2>/dev/null || true
  done
  cg=$(cgroup_dir)
  if [ -n "$cg" ] && [ -d "$cg" ]; then
    for i in "$cg"/node*; do [ -d "$i" ] && rmdir "$i" 2>/dev/null || true; done
    rmdir "$cg" 2>/dev/null || say "could not remove cgroup $cg"
  fi
  left=$(ip netns list 2>/dev/null | awk '{print $1}' | grep -E "^$NAME-" || true)
  left+=$(ip -o link show 2>/dev/null | awk -F': ' '{print $2}' | grep -E "^$NAME-" || true)
  for i in "$STATE"/sid-*; do
    if [ -f "$i" ]; then left+=$(session_pids "$(cat "$i")"); fi
  done
  [ -z "$left" ] || die "down: still there: $(echo $left)"
  rm -rf "$STATE"
  say "down: nothing of cluster $NAME left"
}

session_pids() {  # the Ray processes of session $1 (the name check guards a reused id)
  local pid
  for pid in $(ps -e -o pid=,sid= | awk -v s="$1" '$2 == s { print $1 }'); do
    tr '\0' ' ' < "/proc/$pid/cmdline" 2>/dev/null | grep ray >/dev/null && echo "$pid"
  done
  return 0
}

main() {
  [ $# -ge 1 ] || usage
  local cmd=$1; shift
  case "$cmd" in
    up) cmd_up "$@" ;;
    down) cmd_down "$@" ;;
    shape) cmd_shape "$@" ;;
    status) cmd_status "$@" ;;
    address) load_state "$@"; cat "$STATE/address" ;;
    raylet-pid) cmd_raylet_pid "$@" ;;
    exec) cmd_exec "$@" ;;
    -h|--help|help) usage 0 ;;
    *) die "unknown command $cmd (up, shape, status, address, raylet-pid, exec, down)" ;;
  esac
}

main "$@"
