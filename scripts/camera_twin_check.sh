#!/usr/bin/env bash
# The reference identification judged on a twin that is a camera (issue 111): a camera built from a
# physical mask by scripts/camera_twin.py, known to the user only by four captures and Tikhonov
# pictures of them made as FlatNet made its rec_* (the true calibration, 3e-4, clipped at zero,
# stretched to 8 bits). Three measures:
#   held-out   calibrate --references's leave-one-out correlation (printed by calibrate)
#   factors    each identified factor against the true one at full resolution (camera_twin.py compare)
#   path       Tikhonov through the identified calibration against Tikhonov through the true one, on
#              the held-out photographs (PSNR and detail kept against the photographs)
# Usage: scripts/camera_twin_check.sh TWIN_DIR RUN_DIR [PHOTOS_DIR]
#   TWIN_DIR from `camera_twin.py build`; FLARE=L adds a fixed flare of mean L (full scale) to every
#   capture; NOISE=on|off (default on); COUNT held-out photographs scored (default 40); FLATNET the
#   binary. Resumable: what exists is reused.
set -euo pipefail
[ $# -ge 2 ] || { echo "usage: $0 TWIN_DIR RUN_DIR [PHOTOS_DIR]" >&2; exit 2; }
twin=$(cd "$1" && pwd)
[ -f "$twin/rig.mat" ] && [ -f "$twin/truth.npz" ] || { echo "$0: $twin is not a twin (camera_twin.py build)" >&2; exit 2; }
mkdir -p "$2" && runs=$(cd "$2" && pwd)
[ "$runs" != "$twin" ] || { echo "$0: RUN_DIR must not be the twin's folder" >&2; exit 2; }
[ -z "${3:-}" ] || photos=$(cd "$3" && pwd)
cd "$(dirname "$0")/.."
repo=$PWD
photos=${photos:-$(cd ../shared/data/images/train && pwd)}
flatnet=${FLATNET:-$repo/build/flatnet}
noise=${NOISE:-on}
flare=${FLARE:-0}
count=${COUNT:-40}
cd "$runs"
if [ ! -f heldout.done ]; then
  "$flatnet" simulate --images "$photos" --camera "$twin/camera.yaml" --seed 1 --only val --exposure 0.3 \
    --noise "$noise" --out heldout --force > /dev/null
  if [ "$flare" != 0 ]; then /usr/bin/python3 "$repo/scripts/camera_twin.py" flare heldout/meas --level "$flare"; fi
  touch heldout.done
fi
(grep -v '^display_gamma' "$twin/camera.yaml"; echo "display_gamma: 1") |
  sed -e "s|^rig: .*|rig: \"$twin/rig.mat\"|" -e "s|^calibration: .*|calibration: \"$twin/calib.mat\"|" > linear.yaml
if [ ! -f references.txt ]; then
  rm -rf refs refs-tik refs-ref && mkdir -p refs
  head -4 heldout/val_meas.txt | while read -r f; do cp "heldout/$f" refs/; done
  "$flatnet" recon --method tikhonov --camera linear.yaml --input refs --out refs-tik > /dev/null 2>&1
  /usr/bin/python3 "$repo/scripts/camera_twin.py" stretch refs-tik refs-ref
  ls refs | sed 's|^|refs/|' > captures.txt
  ls refs-ref/*.png > references.txt
fi
if [ ! -f cal/calib.mat ]; then
  mkdir -p cal
  "$flatnet" calibrate --references --meas-list captures.txt --gt-list references.txt --root . \
    --camera linear.yaml --out cal/calib.mat ${CALIBRATE_FLAGS:-} > cal.log 2>&1 || { tail -5 cal.log; exit 1; }
fi
grep -i -E "held-out|correlation|shift" cal.log | tail -4
/usr/bin/python3 "$repo/scripts/camera_twin.py" compare "$twin/truth.npz" cal/calib.mat
# The path: Tikhonov through each calibration on the scored photographs (not the user's four).
tail -n +5 heldout/val_meas.txt | head -"$count" | sed 's|^|heldout/|' > scored.txt
rm -rf scored && mkdir -p scored && while read -r f; do cp "$f" scored/; done < scored.txt
sed -e "s|^calibration: .*|calibration: \"$runs/cal/calib.mat\"|" linear.yaml > identified.yaml
for which in linear identified; do
  "$flatnet" recon --method tikhonov --camera $which.yaml --input scored --out "tik-$which" > /dev/null 2>&1
done
/usr/bin/python3 "$repo/scripts/camera_twin.py" score heldout/gt tik-linear tik-identified
