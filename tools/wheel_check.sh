#!/usr/bin/env bash
# `make wheel-check`: build the wheel, install it (dependencies from constraints.txt) into a clean venv outside
# the repository, and run `pixie demo` and `pixie estimate` on the generated part from an empty folder with no
# shared data folder, no PIXIE_WEIGHTS, an empty HOME and (where `unshare -rn` works) no network.
# The demo and estimate use --preset fast (46 reference views) to keep the check near 2 minutes.
# Everything the installed package needs must come with it. Takes ~2 min with a warm pip cache.
set -euo pipefail
REPO="$(cd "$(dirname "$0")/.." && pwd)"
PY="${PY:-python3}"
PIP_VERSION="${PIP_VERSION:-26.3}"
TMP="$(mktemp -d "${TMPDIR:-/tmp}/pixie-wheel-check.XXXXXX")"
trap 'rm -rf "$TMP"' EXIT
say() { printf '\n== wheel-check: %s\n' "$*"; }

say "building the wheel (from a clean copy of the working tree: a stale build/ folder would leak old modules)"
mkdir -p "$TMP/src"
(cd "$REPO" && tar -cf - --exclude=./.git --exclude=./.venv --exclude=./build --exclude=./out --exclude='*.egg-info' \
   --exclude=__pycache__ --exclude=./.lockenv .) | tar -xf - -C "$TMP/src"
"$PY" -m venv "$TMP/build-venv"
"$TMP/build-venv/bin/pip" install -q "pip==$PIP_VERSION"
"$TMP/build-venv/bin/pip" wheel -q --no-deps -w "$TMP/dist" "$TMP/src"
WHEEL="$(ls "$TMP"/dist/pixie_pose-*.whl)"
ls -l "$WHEEL"
unzip -l "$WHEEL" | grep -E "data/weights/aliked-n16.pth|LICENSE-ALIKED|PROVENANCE|configs/default.yaml" \
  || { echo "wheel-check: the wheel lacks its weights, licence, provenance or presets" >&2; exit 1; }
if unzip -l "$WHEEL" | grep -qE " pixie/(matching|eval)\.py$"; then
  echo "wheel-check: the wheel holds a stale module next to its package (pixie/matching.py or pixie/eval.py)" >&2; exit 1
fi

say "installing it into a clean venv (constraints.txt)"
"$PY" -m venv "$TMP/venv"
"$TMP/venv/bin/pip" install -q "pip==$PIP_VERSION"
"$TMP/venv/bin/pip" install -q -c "$REPO/constraints.txt" "$WHEEL"
"$TMP/venv/bin/pip" check

mkdir -p "$TMP/run" "$TMP/home"
NONET=()
if unshare -rn true 2>/dev/null; then NONET=(unshare -rn); else echo "(unshare -rn not available: network not cut)"; fi
run() {  # offline, empty HOME, no shared folder, no PIXIE_WEIGHTS, from an empty folder outside the repo
  (cd "$TMP/run" && env -u PIXIE_WEIGHTS -u PIXIE_SHARED HOME="$TMP/home" XDG_CACHE_HOME="$TMP/home/.cache" \
     "${NONET[@]}" "$TMP/venv/bin/$1" "${@:2}")
}
run pixie --version
run python -c "import pixie, sys; p = pixie.__file__; sys.exit(0 if '$REPO' not in p else 'pixie imported from the repo: ' + p)"
say "pixie weights"
run pixie weights | grep -E "^(aliked-nn|aliked-n16) "
say "pixie demo (generated part; preset fast to keep the check short)"
run pixie demo --preset fast --out "$TMP/run/demo"
say "pixie estimate on the generated part"
D="$TMP/run/demo"
run pixie estimate --preset fast --refs "$(ls "$TMP"/home/.cache/pixie/refs/*.npz | head -1)" --image "$D/photo.png" --K "$(cat "$D/K.txt")" \
  --bbox "$(cat "$D/bbox.txt")" -o "$D/result.json" --overlay "$D/estimate.png"
test -s "$D/result.json" && test -s "$D/estimate.png"
say "check your setup: pixie render -> pixie estimate --gt"
run pixie render --mesh "$D/part.stl" -o "$D/check" --seed 3
S="$D/check/scene.json"
K_ARG="$("$TMP/venv/bin/python" -c "import json,sys; print(json.load(open(sys.argv[1]))['K_arg'])" "$S")"
BOX="$("$TMP/venv/bin/python" -c "import json,sys; print(','.join(map(str, json.load(open(sys.argv[1]))['bbox_xywh'])))" "$S")"
run pixie estimate --preset fast --refs "$(ls "$TMP"/home/.cache/pixie/refs/*.npz | head -1)" --image "$D/check/photo.png" --K "$K_ARG" \
  --bbox "$BOX" --gt "$D/check/gt_pose.json" | tee "$D/check/estimate.txt"
grep -q "error against --gt" "$D/check/estimate.txt"
say "OK: the installed wheel runs offline with no shared data"
