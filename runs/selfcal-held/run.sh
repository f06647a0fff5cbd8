#!/bin/sh
# The runs of runs/selfcal-held/README.md: bench/selfcal.py's four runs and rti-icon with
# --self-calibrate, for one variant (unread or always). Logs beside this file.
# Usage: sh runs/selfcal-held/run.sh MODE   (rti-icon imported first: matscan import-rti
# tests/data/rti-icon --out /tmp/icon)
set -e
mode=$1
d=runs/selfcal-held
py=.venv/bin/python
$py bench/selfcal.py 128 --held=$mode > $d/selfcal-128-$mode.log 2>&1
$py bench/selfcal.py 128 --held-out --held=$mode > $d/selfcal-128heldout-$mode.log 2>&1
if [ "$mode" = unread ]; then  # B (always) is judged at 128² only (README.md)
    $py bench/selfcal.py 256 --held=$mode > $d/selfcal-256-$mode.log 2>&1
    $py bench/selfcal.py 256 --held-out --held=$mode > $d/selfcal-256heldout-$mode.log 2>&1
fi
rm -rf /tmp/icon-$mode
$py -c "
import sys
from matscan.reconstruct import selfcal
selfcal.HELD_GAINS = '$mode'
from matscan.cli import main
sys.argv = ['matscan', 'reconstruct', '/tmp/icon', '--out', '/tmp/icon-$mode', '--validate', '18', '--self-calibrate']
main()
" > $d/rti-icon-$mode.log 2>&1
$py -c "
import json
v = json.load(open('/tmp/icon-$mode/matscan.json'))['validation']
print(json.dumps(v, indent=1)[:1500])
" >> $d/rti-icon-$mode.log
