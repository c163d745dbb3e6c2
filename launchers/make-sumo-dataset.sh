#!/usr/bin/env bash
# Make a dataset of driving scenes with the Eclipse SUMO traffic simulator, reproducibly.
#
#   launchers/make-sumo-dataset.sh OUT [options]
#
# For each network generator (grid, spider, rand) it builds a road network with sidewalks, crossings and
# traffic lights (netgenerate), makes vehicle, bicycle and pedestrian demand (randomTrips.py), simulates
# it at 0.1 s recording every 0.5 s (sumo --fcd-output) and every traffic light's state (SaveTLSStates),
# and imports both (umgen data sumo --tls).
# SUMO comes from PyPI (eclipse-sumo) into a virtual environment, installed on first use.
#
# Options:
#   --seed N            base seed (default 1); network k uses seed N+k
#   --duration S        recorded seconds per network (default 300)
#   --warmup S          simulated seconds before recording starts (default 60)
#   --networks "..."    generators to use, in order (default "grid spider rand")
#   --test "..."        generators whose clips form the test split (default: none)
#   --demand K          traffic multiplier (default 1.0)
#   --ego-every N       every n-th car becomes an ego (default 1)
#   --umgen CMD         the umgen command (default: cargo run --release -q -p umgen-cli --)
#   --work DIR          keep SUMO's files here (default: a temporary directory, removed afterwards)
#   --force             replace OUT if it exists
#   --append            add the networks to the dataset already in OUT (new names: pick another --seed)
# Environment: UMGEN_SUMO_VENV (default ~/.cache/umgen/sumo-venv), UMGEN_SUMO_VERSION (default 1.28.0).
set -euo pipefail

die() { echo "make-sumo-dataset: $*" >&2; exit 1; }
[ $# -ge 1 ] || die "usage: $0 OUT [--seed N] [--duration S] [--networks \"grid spider rand\"] ..."
OUT=$1; shift
SEED=1 DURATION=300 WARMUP=60 NETWORKS="grid spider rand" TEST="" DEMAND=1.0 EGO_EVERY=1 WORK="" FORCE=0 APPEND=0
UMGEN="cargo run --release -q -p umgen-cli --"
while [ $# -gt 0 ]; do
  case $1 in
    --seed) SEED=$2; shift 2 ;;
    --duration) DURATION=$2; shift 2 ;;
    --warmup) WARMUP=$2; shift 2 ;;
    --networks) NETWORKS=$2; shift 2 ;;
    --test) TEST=$2; shift 2 ;;
    --demand) DEMAND=$2; shift 2 ;;
    --ego-every) EGO_EVERY=$2; shift 2 ;;
    --umgen) UMGEN=$2; shift 2 ;;
    --work) WORK=$2; shift 2 ;;
    --force) FORCE=1; shift ;;
    --append) APPEND=1; shift ;;
    *) die "unknown option $1" ;;
  esac
done
if [ "$APPEND" = 1 ]; then
  [ "$FORCE" = 0 ] || die "--append and --force exclude each other"
  [ -f "$OUT/index.json" ] || die "--append: $OUT holds no dataset (no index.json)"
elif [ -e "$OUT" ]; then
  [ "$FORCE" = 1 ] || die "$OUT exists (use --force to replace it, --append to add to it)"
  rm -rf "$OUT"
fi

VENV=${UMGEN_SUMO_VENV:-$HOME/.cache/umgen/sumo-venv}
VERSION=${UMGEN_SUMO_VERSION:-1.28.0}
if [ ! -x "$VENV/bin/sumo" ]; then
  echo "make-sumo-dataset: installing eclipse-sumo==$VERSION into $VENV" >&2
  python3 -m venv "$VENV" || die "python3 -m venv failed"
  "$VENV/bin/pip" install -q "eclipse-sumo==$VERSION" || die "pip install eclipse-sumo==$VERSION failed (no network?)"
fi
VENV=$(cd "$VENV" && pwd)
export SUMO_HOME
SUMO_HOME=$("$VENV/bin/python" -c 'import sumo, os; print(os.path.dirname(sumo.__file__))')
PY="$VENV/bin/python"; BIN="$VENV/bin"; TOOLS="$SUMO_HOME/tools"

if [ -z "$WORK" ]; then WORK=$(mktemp -d); trap 'rm -rf "$WORK"' EXIT; fi
mkdir -p "$WORK"; WORK=$(cd "$WORK" && pwd)  # absolute: randomTrips runs inside it

# Vehicle mix with explicit sizes (m), so nothing depends on SUMO's class defaults.
cat > "$WORK/vtypes.add.xml" <<'XML'
<additional>
    <vTypeDistribution id="u_vehicles">
        <vType id="u_sedan" vClass="passenger" length="4.6" width="1.8" height="1.45" probability="0.45" speedFactor="normc(1,0.1,0.2,2)"/>
        <vType id="u_suv" vClass="passenger" length="4.9" width="1.95" height="1.75" probability="0.25" speedFactor="normc(1,0.1,0.2,2)"/>
        <vType id="u_van" vClass="delivery" length="5.6" width="2.0" height="2.3" probability="0.1"/>
        <vType id="u_truck" vClass="truck" length="8.5" width="2.5" height="3.3" probability="0.07"/>
        <vType id="u_bus" vClass="bus" length="12.0" width="2.55" height="3.2" probability="0.05"/>
        <vType id="u_motorbike" vClass="motorcycle" length="2.2" width="0.8" height="1.5" probability="0.08"/>
    </vTypeDistribution>
    <vType id="u_bike" vClass="bicycle" length="1.8" width="0.65" height="1.7"/>
    <vType id="u_walker" vClass="pedestrian" length="0.3" width="0.55" height="1.75"/>
</additional>
XML

COMMON="--default.lanenumber 2 --sidewalks.guess --crossings.guess --tls.guess --no-turnarounds --junctions.corner-detail 10"
period() { awk -v p="$1" -v k="$DEMAND" 'BEGIN { printf "%.3f", p / k }'; }
END=$((WARMUP + DURATION))
k=0
for gen in $NETWORKS; do
  seed=$((SEED + k)); k=$((k + 1))
  name="$gen-s$seed"; w="$WORK/$name"; mkdir -p "$w"
  case $gen in
    grid) args="--grid --grid.number 4 --grid.length 130 --default.junctions.type traffic_light" ;;
    spider) args="--spider --spider.arm-number 5 --spider.circle-number 3 --spider.space-radius 90" ;;
    rand) args="--rand --rand.iterations 60 --rand.min-distance 70 --rand.max-distance 180" ;;
    *) die "unknown network generator $gen (grid, spider, rand)" ;;
  esac
  echo "make-sumo-dataset: $name: network" >&2
  # shellcheck disable=SC2086
  "$BIN/netgenerate" $args $COMMON --seed "$seed" -o "$w/net.net.xml" >"$w/netgenerate.log" 2>&1 || die "netgenerate failed: $w/netgenerate.log"
  echo "make-sumo-dataset: $name: demand" >&2
  # randomTrips --validate leaves routes.rou.xml in the working directory: run it in the network's folder.
  trips() { (cd "$w" && "$PY" "$TOOLS/randomTrips.py" -n "$w/net.net.xml" --additional-files "$WORK/vtypes.add.xml" -b 0 -e "$END" "$@" >>"$w/trips.log" 2>&1) || die "randomTrips failed: $w/trips.log"; }
  trips -o "$w/veh.trips.xml" --seed "$seed" -p "$(period 1.2)" --prefix v --fringe-factor 5 --validate --trip-attributes 'type="u_vehicles"'
  trips -o "$w/bike.trips.xml" --seed $((seed + 1000)) -p "$(period 8)" --prefix b --vclass bicycle --validate --trip-attributes 'type="u_bike"'
  trips -o "$w/ped.trips.xml" --seed $((seed + 2000)) -p "$(period 3)" --prefix p --pedestrians --max-distance 800 --trip-attributes 'type="u_walker"'
  echo "make-sumo-dataset: $name: simulation" >&2
  # Every traffic light's state at every step (the importer keeps those of the recorded steps).
  printf '<additional>\n    <timedEvent type="SaveTLSStates" dest="%s"/>\n</additional>\n' "$w/tls.xml" >"$w/tls.add.xml"
  "$BIN/sumo" -n "$w/net.net.xml" -a "$WORK/vtypes.add.xml,$w/tls.add.xml" -r "$w/veh.trips.xml,$w/bike.trips.xml,$w/ped.trips.xml" \
    --step-length 0.1 --device.fcd.period 0.5 --device.fcd.begin "$WARMUP" --end "$END" --lanechange.duration 2 \
    --time-to-teleport 120 --seed "$seed" --no-step-log --no-warnings --fcd-output "$w/fcd.xml" >"$w/sumo.log" 2>&1 \
    || die "sumo failed: $w/sumo.log"
  split=train
  case " $TEST " in *" $gen "*) split=test ;; esac
  echo "make-sumo-dataset: $name: import ($split)" >&2
  # shellcheck disable=SC2086
  $UMGEN data sumo --net "$w/net.net.xml" --fcd "$w/fcd.xml" --tls "$w/tls.xml" --types "$WORK/vtypes.add.xml" \
    --out "$OUT" --name "$name" --network-name "$name" --split "$split" --ego-every "$EGO_EVERY"
done
echo "make-sumo-dataset: wrote $OUT" >&2
