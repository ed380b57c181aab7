#!/usr/bin/env bash
# Check the ComfyUI install routes of docs/comfyui.md with a real ComfyUI, each from a clean clone of this
# repository's HEAD and in its own copy of ComfyUI's Python environment.
#
# usage: tools/check_install_routes.sh ROOT [ROUTE...]
#   ROOT   a folder holding ComfyUI/ (a ComfyUI checkout; its main.py must take --base-directory,
#          as 0.3.64 does) and venv/ (a Python environment in which that ComfyUI runs, with nothing
#          of this pack installed: docs/comfyui.md, "Integration tests", makes one)
#   ROUTE  git      clone into custom_nodes/artnvg, then `pip install -e artnvg` (the git route,
#                   also comfy-cli's)
#          manager  clone into custom_nodes/artnvg-comfyui, then `pip install -r requirements.txt` when
#                   there is one (what ComfyUI Manager's "Install via Git URL" and the Comfy registry do)
#          pip-git  clone into custom_nodes/artnvg, then `pip install git+URL` (the library from git,
#                   not editable: checks that the package carries its demo and data files)
#          default: all three
#
# Each route gets ROOT/routes/ROUTE/: a copy of ROOT/venv, and a ComfyUI base directory (custom
# nodes, input, output) that ROOT/ComfyUI runs on (--base-directory, CPU, a free port). A route
# passes when the server starts, lists every node of the pack (nodes/__init__.py), logs no import
# failure, and runs the NNFM demo workflow (docs/comfyui.md: the demo copied to input/artnvg_demo/,
# workflows/artnvg_nnfm_only_api.json at small settings, queued with workflows/queue_workflow.py)
# to a saved scene. Logs: ROOT/routes/ROUTE/*.log. Exit status 0 when every route passed.
set -uo pipefail
ROOT=$(cd "${1:?usage: tools/check_install_routes.sh ROOT [git|manager|pip-git ...]}" && pwd); shift
if [ $# -gt 0 ]; then ROUTES=("$@"); else ROUTES=(git manager pip-git); fi
REPO=$(cd "$(dirname "$0")/.." && pwd)
COMMIT=$(git -C "$REPO" rev-parse HEAD)
[ -f "$ROOT/ComfyUI/main.py" ] && [ -x "$ROOT/venv/bin/python" ] || { echo "$ROOT needs ComfyUI/main.py and venv/bin/python"; exit 2; }

SMALL=(--set "Render Views.scale=0.125" --set "Render Views.stride=6"  # 4 of the 24 demo views, 64x64
       --set "Finetune Gaussians.iterations=10"
       --set "Render Camera Path.scale=0.125" --set "Render Camera Path.num_frames=4")

# install ROUTE DIR PYTHON: the clone into DIR/base/custom_nodes and the route's pip command
install() {
  local route=$1 nodes="$2/base/custom_nodes" python=$3
  case $route in
    git)     git clone -q "$REPO" "$nodes/artnvg" && (cd "$nodes" && "$python" -m pip install -q -e artnvg) ;;
    manager) git clone -q "$REPO" "$nodes/artnvg-comfyui" &&  # as Manager: no requirements.txt, no install
             (cd "$nodes/artnvg-comfyui" && { [ ! -f requirements.txt ] || "$python" -m pip install -q -r requirements.txt; }) ;;
    pip-git) git clone -q "$REPO" "$nodes/artnvg" && "$python" -m pip install -q "git+file://$REPO@$COMMIT" ;;
    *) echo "unknown route $route"; return 2 ;;
  esac
}

# check_route ROUTE: 0 when the route installs, loads and runs the demo workflow
check_route() {
  local route=$1 dir="$ROOT/routes/$1" python pack port url server status=0
  rm -rf "$dir" && mkdir -p "$dir"/base/{custom_nodes,input,output,user}
  echo "-- $route: copying ComfyUI's environment"
  cp -a "$ROOT/venv" "$dir/venv" || return 1
  python="$dir/venv/bin/python"
  echo "-- $route: installing"
  install "$route" "$dir" "$python" > "$dir/install.log" 2>&1 || { tail -20 "$dir/install.log"; return 1; }
  pack=$(ls -d "$dir"/base/custom_nodes/artnvg*)
  cp -r "$pack/artnvg_core/demo" "$dir/base/input/artnvg_demo"
  port=$("$python" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
  url="http://127.0.0.1:$port"
  echo "-- $route: starting ComfyUI on $url"
  (cd "$ROOT/ComfyUI" && exec "$python" main.py --cpu --listen 127.0.0.1 --port "$port" \
      --base-directory "$dir/base") > "$dir/server.log" 2>&1 &
  server=$!
  "$python" - "$url" "$server" "$pack/nodes/__init__.py" <<'EOF' || status=1
import json, os, re, sys, time, urllib.request
url, pid, mappings = sys.argv[1], int(sys.argv[2]), open(sys.argv[3]).read()
deadline = time.monotonic() + 300
while True:
    try:
        with urllib.request.urlopen(url + "/object_info", timeout=30) as response:
            listed = {name for name in json.load(response) if name.startswith("ArtNVG")}
        break
    except OSError:
        if time.monotonic() > deadline or not os.path.exists(f"/proc/{pid}"):
            sys.exit("ComfyUI did not start (server.log)")
        time.sleep(1)
packed = set(re.findall(r'^ *"(ArtNVG\w+)":', mappings, re.MULTILINE))  # NODE_CLASS_MAPPINGS' keys
missing = sorted(packed - listed)
print(f"ComfyUI lists {len(listed)} of the pack's {len(packed)} nodes" + (f"; missing: {missing}" if missing else ""))
sys.exit(1 if missing or not packed else 0)
EOF
  if grep -n -E "IMPORT FAILED|Cannot import .*artnvg" "$dir/server.log"; then status=1; fi
  if [ $status -eq 0 ]; then
    echo "-- $route: queueing the demo workflow"
    "$python" "$pack/workflows/queue_workflow.py" "$pack/workflows/artnvg_nnfm_only_api.json" \
        --server "$url" --timeout 900 "${SMALL[@]}" > "$dir/queue.log" 2>&1 || status=1
    tail -5 "$dir/queue.log"
    ls "$dir"/base/output/artnvg/nnfm*.ply > /dev/null 2>&1 || { echo "no scene saved"; status=1; }
  fi
  kill "$server" 2> /dev/null; wait "$server" 2> /dev/null
  [ $status -eq 0 ] || tail -20 "$dir/server.log"
  return $status
}

declare -A RESULT
for route in "${ROUTES[@]}"; do
  start=$SECONDS
  if check_route "$route"; then RESULT[$route]=passed; else RESULT[$route]=FAILED; fi
  RESULT[$route]+=" ($((SECONDS - start)) s)"
done
echo
VERSION=$(sed -n 's/^__version__ = "\(.*\)"/\1/p' "$ROOT/ComfyUI/comfyui_version.py" 2>/dev/null)
echo "commit $COMMIT, $(date -u +%F), ComfyUI ${VERSION:-(version unknown)} in $ROOT, $("$ROOT/venv/bin/python" --version 2>&1)"
failed=0
for route in "${ROUTES[@]}"; do
  echo "  $route: ${RESULT[$route]}"
  [[ ${RESULT[$route]} == passed* ]] || failed=1
done
exit $failed
