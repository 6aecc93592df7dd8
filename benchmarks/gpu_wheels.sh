# Sourced by the GPU scripts: install the wheels of directory $1 (if any) into /tmp/site with
# python $2 and put /tmp/site on PYTHONPATH.
#
#   source benchmarks/gpu_wheels.sh .whl python3
#
# The install is skipped when /tmp/site already holds this exact set of wheels (a second call on a
# machine that is still warm): reinstalling gives gsplat's sources new modification times, and its
# JIT loader then rebuilds the CUDA extension (60-75 s on an H200) although nothing changed.
_wheel_dir=${1:-.whl}
_wheel_python=${2:-python3}
if ls "$_wheel_dir"/*.whl >/dev/null 2>&1; then
    _wheel_stamp=$(cd "$_wheel_dir" && ls -l --time-style=+%s *.whl | awk '{print $5, $6, $7}')
    if [ -f /tmp/site/.wheels ] && [ "$(cat /tmp/site/.wheels)" = "$_wheel_stamp" ]; then
        echo "[gpu_wheels] /tmp/site already holds these wheels: not reinstalled (keeps gsplat's built extension)"
        export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
    elif "$_wheel_python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target /tmp/site "$_wheel_dir"/*.whl; then
        echo "$_wheel_stamp" > /tmp/site/.wheels
        export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
    else
        echo "[gpu_wheels] installing the wheels of $_wheel_dir failed" >&2
    fi
fi
