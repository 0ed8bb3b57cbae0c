"""Plain averaging with NO border cut at the points `govnesf evaluate` scores (docs/how-to/evaluate.md).

`mapper.model.baselines.average_features` cuts a 10 px image border (OpenScene-2D); the model blends
every view the point projects into. This prints averaging over the same candidate views as the
model (0 px border), without depth and with the 25% depth test, per style, on the same point
subsets as `govnesf evaluate --max-points 20000` (same seed).

Usage: python benchmarks/studies/averaging_border.py [DATA_DIR ...]   (default data/eval)
"""

import sys

import numpy as np
import torch

from mapper.model.baselines import average_features
from mapper.ov.encoders import get_text_encoder
from mapper.training import evaluate as ev
from mapper.training.metrics import average_over_scenes, predict_labels, scores_from_labels

settings = ev.EvalSettings(max_points=20000)
res = {}
text = None
for d in ev.find_scene_dirs(sys.argv[1:] or ["data/eval"]):
    s = ev.load_scene(d)
    if text is None:
        text = torch.from_numpy(get_text_encoder().encode(s.class_names[:20]))
    keep = ev._subset(s, settings)
    pts = torch.from_numpy(s.points_xyz[keep])
    gt = s.points_label[keep]
    views = ev._avg_views(s)
    for depth in (False, True):
        f, _ = average_features(pts, views, use_depth=depth, border_px=0.0)
        pred = np.asarray(predict_labels(f, text))
        res.setdefault((s.style, depth), []).append(scores_from_labels(gt, pred))
for (style, depth), sc in sorted(res.items()):
    a = average_over_scenes(sc)
    name = "Averaging + depth test" if depth else "Averaging (no depth)"
    print(f"| {style} | {name}, 0 px border | {100 * a.miou:.1f} | {100 * a.macc:.1f} | {100 * a.oacc:.1f} |")
