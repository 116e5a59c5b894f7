"""J1 step (1): today's default and J1 on the 24-pair validation set (int8, the default's pass), paired changes;
the indoor set's teacher bad-3 beside it. Usage: python j1_score.py OUT"""
import json
import sys
import warnings
from pathlib import Path

import torch

from optstereo.api import load_model
from optstereo.inference.fastpath import engineering
from optstereo.validation import PairScore, open_valset, paired_difference, pooled, score

warnings.simplefilter("error")  # a sidecar of other weights must not silently turn int8 off
torch.set_num_threads(2)
out = Path(sys.argv[1])
out.mkdir(parents=True, exist_ok=True)
files = {"v15": "pretrained", "j1": "/work/t14/j1/optstereo_kitti_pvm.safetensors"}
res = {}
for setname, root in (("val", "/work/valset"), ("indoor", "/work/val_indoor")):
    for name, spec in files.items():
        path = out / f"{setname}_{name}.json"
        if path.exists():
            res[setname, name] = [PairScore(**p) for p in json.loads(path.read_text())["pairs"]]
            continue
        with engineering(True, int8=True):
            model = load_model(spec)
            pairs = score(model, open_valset(root), progress=False, what=name).pairs
        doc = {"spec": spec, "summary": pooled(pairs), "pairs": [vars(p) for p in pairs]}
        path.write_text(json.dumps(doc, indent=1))
        res[setname, name] = pairs
        print(setname, name, json.dumps(pooled(pairs)), flush=True)
for setname in ("val", "indoor"):
    print(f"== {setname}")
    for key in ("pvm_epe", "teacher_epe", "pvm_bad3", "teacher_bad3", "photometric"):
        d, m = paired_difference(res[setname, "v15"], res[setname, "j1"], key)
        a, b = pooled(res[setname, "v15"])[key], pooled(res[setname, "j1"])[key]
        print(f"  {key}: {a:.4f} -> {b:.4f}  per-pair change {d:+.4f} (2 SE {m:.4f})")
