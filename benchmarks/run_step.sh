# Sourced by the prepared device scripts (device_check.sh, lab/device_gap.sh): the interpreter they
# run and how each of their steps runs. Not a script of its own.

# benchmark_python ROOT: prints the interpreter to run: PYTHON where set (refused in one line,
# status 2, where it is no interpreter here), else ROOT's .venv's, else python3 on the PATH.
benchmark_python() {
    if [ -n "${PYTHON:-}" ]; then
        command -v "$PYTHON" || { echo "error: PYTHON=$PYTHON is not a Python interpreter here" >&2; return 2; }
    else
        command -v "$1/.venv/bin/python" || command -v python3 || command -v python
    fi
}

# run_step NAME SECONDS COMMAND...: runs COMMAND under a time limit, its output in $out_dir/NAME.log;
# its exit status and wall seconds go to $out_dir/NAME.status.json and, as a line that is also
# printed, to $out_dir/status.txt. A failed or timed-out step does not stop the script.
run_step() {
    local name=$1 seconds=$2 start=$SECONDS
    shift 2
    timeout "$seconds" "$@" >"$out_dir/$name.log" 2>&1
    local code=$?
    echo "{\"step\": \"$name\", \"exit_code\": $code, \"wall_seconds\": $((SECONDS - start))}" >"$out_dir/$name.status.json"
    echo "$name: exit $code in $((SECONDS - start)) s" | tee -a "$out_dir/status.txt"
}
