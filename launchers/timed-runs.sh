# Sourced by the speed launchers: `run NAME COMMAND...` runs the command under `timeout "$limit"`, its
# output in "$out/NAME.txt", and appends its exit status and seconds to "$out/summary.txt" (and prints
# them), so that one slow or failing case cannot take the others with it. The caller sets `out` and `limit`.
run() { # name command...
    local name=$1 t0
    shift
    t0=$(date +%s)
    timeout "$limit" "$@" >"$out/$name.txt" 2>&1
    echo "== $name: exit $? after $(($(date +%s) - t0)) s" | tee -a "$out/summary.txt"
}
