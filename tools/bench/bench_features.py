"""Local features: our SURF against OpenCV SIFT per image, the ORB pair against raw OpenCV calls,
and (--accuracy) every detector + matcher on the public ground truth.

Timing (process CPU seconds, minimum over interleaved rounds, graf img1 800x640 and the same
resized to 640x480 with INTER_AREA):
- surf_vs_sift: `trundle.perception.surf.surf` (defaults) / `cv2.SIFT.create().detectAndCompute`
  (goal <= 3);
- orb_pair: `image_matching.match_images(..., "orb", max_keypoints=1000)` without RANSAC's
  share, i.e. 2 x detect_and_describe + `matching.match` (cross-check, ratio 0.8) /
  2 x `ORB_create(1000).detectAndCompute` + `BFMatcher(NORM_HAMMING).knnMatch(k=2)` with the
  same ratio and cross-check filters.

Accuracy (--accuracy, slow): graf 1->2..1->6 and v_churchill 1->2..1->6 at native resolution,
grey via cvtColor, the 2000 strongest keypoints per image, brute-force matching (cross-check,
ratio 0.8), our RANSAC homography (3 px). Per pair: max corner error of image 1's corners
against the ground truth (pass: <= 3 px), repeatability and matching score at 3 px
(perception/feature_eval.py). `--markdown FILE` writes the table (docs/features.md).
Run: python tools/bench/bench_features.py [--repeat N] [--accuracy [--markdown docs/features.md]]
"""

from __future__ import annotations

import argparse
import time
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from trundle.logs.outputs import write_json
from trundle.perception.feature_eval import corner_error, matching_score, repeatability
from trundle.perception.features import METHODS, Features, available, detect_and_describe
from trundle.perception.image_matching import match_features
from trundle.perception.keypoints import from_cv
from trundle.perception.matching import match
from trundle.perception.surf import surf
from trundle.tools.bench import report

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
SEQUENCES = {"graf": ("oxford/graf/img{}.png", "oxford/graf/H1to{}p"),
             "v_churchill": ("hpatches/v_churchill/{}.png", "hpatches/v_churchill/H_1_{}")}
BUDGET = 2000
PASS_PX = 3.0


def cpu(fn, rounds: int = 1) -> float:
    start = time.process_time()
    for _ in range(rounds):
        fn()
    return (time.process_time() - start) / rounds


def load(relative: str) -> np.ndarray:
    path = DATA / relative
    image = cv2.imread(str(path))
    if image is None:
        raise SystemExit(f"public data not available: {path} (see ../shared/data/README.md)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def raw_orb_pair(a: np.ndarray, b: np.ndarray) -> int:
    orb = cv2.ORB.create(1000)
    ka, da = orb.detectAndCompute(a, None)
    kb, db = orb.detectAndCompute(b, None)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    forward = matcher.knnMatch(da, db, k=2)
    backward = {m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(db, da, k=1)}
    good = [m[0] for m in forward if len(m) == 2 and m[0].distance <= 0.8 * m[1].distance]
    return sum(1 for m in good if backward.get(m.trainIdx) == m.queryIdx)


def our_orb_pair(a: np.ndarray, b: np.ndarray) -> int:
    fa = detect_and_describe(a, "orb", max_keypoints=1000)
    fb = detect_and_describe(b, "orb", max_keypoints=1000)
    return len(match(fa.descriptors, fb.descriptors, fa.metric, max_ratio=0.8).pairs)


def timing(repeat: int) -> dict[str, float]:
    graf1, graf2 = load("oxford/graf/img1.png"), load("oxford/graf/img2.png")
    small1, small2 = (cv2.resize(g, (640, 480), interpolation=cv2.INTER_AREA) for g in (graf1, graf2))
    sift = cv2.SIFT.create()
    figures: dict[str, float] = {}
    for name, image in (("graf_800x640", graf1), ("graf_640x480", small1)):
        best = {"surf": float("inf"), "sift": float("inf")}
        for _ in range(repeat):
            best["surf"] = min(best["surf"], cpu(partial(surf, image)))
            best["sift"] = min(best["sift"], cpu(partial(sift.detectAndCompute, image, None)))
        figures[f"{name}_surf_keypoints"] = len(surf(image)[0])
        figures[f"{name}_sift_keypoints"] = len(sift.detect(image, None))
        figures[f"{name}_surf_ms"] = best["surf"] * 1e3
        figures[f"{name}_sift_ms"] = best["sift"] * 1e3
        figures[f"{name}_surf_vs_sift"] = best["surf"] / best["sift"]
    best = {"ours": float("inf"), "raw": float("inf")}
    for _ in range(repeat):
        best["ours"] = min(best["ours"], cpu(lambda: our_orb_pair(small1, small2)))
        best["raw"] = min(best["raw"], cpu(lambda: raw_orb_pair(small1, small2)))
    figures["orb_pair_640x480_matches"] = our_orb_pair(small1, small2)
    figures["orb_pair_640x480_raw_matches"] = raw_orb_pair(small1, small2)
    figures["orb_pair_640x480_ms"] = best["ours"] * 1e3
    figures["orb_pair_640x480_raw_ms"] = best["raw"] * 1e3
    figures["orb_pair_640x480_ratio"] = best["ours"] / best["raw"]
    return figures


def surf_against_sift() -> dict[str, float]:
    """Matching score of our SURF and of OpenCV SIFT on graf 1->2 and 1->3: the 2000 strongest
    keypoints each, brute-force L2 with cross-check, correct within 3 px (as tests/test_surf.py)."""
    images = {i: load(f"oxford/graf/img{i}.png") for i in (1, 2, 3)}
    sift = cv2.SIFT.create(nfeatures=BUDGET)
    feats = {"surf": {i: surf(img, hessian_threshold=300, max_keypoints=BUDGET) for i, img in images.items()},
             "sift": {}}
    for i, img in images.items():
        found, desc = sift.detectAndCompute(img, None)
        feats["sift"][i] = (from_cv(found), desc)
    figures = {}
    for j in (2, 3):
        h = np.loadtxt(DATA / f"oxford/graf/H1to{j}p")
        for name in ("surf", "sift"):
            (k1, d1), (k2, d2) = feats[name][1], feats[name][j]
            pairs = match(d1, d2, "l2").pairs
            figures[f"graf_1-{j}_{name}_matching_score"] = matching_score(k1, k2, pairs, h, images[1].shape,
                                                                          images[j].shape)[0]
        figures[f"graf_1-{j}_surf_over_sift"] = (figures[f"graf_1-{j}_surf_matching_score"]
                                                 / figures[f"graf_1-{j}_sift_matching_score"])
    return figures


def evaluate(methods: list[str]) -> list[dict]:
    """One row per (method, sequence, pair) with corner error, repeatability, matching score."""
    rows = []
    for sequence, (image_path, h_path) in SEQUENCES.items():
        images = {i: load(image_path.format(i)) for i in range(1, 7)}
        for method in methods:
            start = time.perf_counter()
            feats: dict[int, Features] = {i: detect_and_describe(img, method, max_keypoints=BUDGET)
                                          for i, img in images.items()}
            for j in range(2, 7):
                h = np.loadtxt(DATA / h_path.format(j))
                pair = match_features(feats[1], feats[j])
                _, worst = corner_error(pair.fit.model, h, images[1].shape)
                rep, _ = repeatability(feats[1].keypoints, feats[j].keypoints, h, images[1].shape, images[j].shape)
                score, precision, _ = matching_score(feats[1].keypoints, feats[j].keypoints, pair.matches.pairs, h,
                                                     images[1].shape, images[j].shape)
                rows.append({"method": method, "sequence": sequence, "pair": f"1-{j}",
                             "keypoints": len(feats[1].keypoints), "matches": len(pair.matches.pairs),
                             "inliers": int(pair.fit.inliers.sum()), "corner_error_px": worst,
                             "pass": bool(worst <= PASS_PX), "repeatability": rep, "matching_score": score,
                             "precision": precision})
            print(f"{sequence} {method}: {time.perf_counter() - start:.1f} s", flush=True)
    return rows


def markdown(rows: list[dict]) -> str:
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lines = []
    for sequence in SEQUENCES:
        pairs = [f"1-{j}" for j in range(2, 7)]
        lines += [f"### {sequence}", "",
                  "max corner error px (pass <= 3 px) / repeatability / matching score, at 3 px", "",
                  "| detector + descriptor | kp | " + " | ".join(pairs) + " | pairs handled |",
                  "|---|---|" + "---|" * len(pairs) + "---|"]
        for method in methods:
            cells, handled, kp = [], [], 0
            for pair in pairs:
                r = next(x for x in rows if x["method"] == method and x["sequence"] == sequence and x["pair"] == pair)
                kp = r["keypoints"]
                error = "fail" if not np.isfinite(r["corner_error_px"]) or r["corner_error_px"] > 99 else \
                    f"{r['corner_error_px']:.1f}"
                mark = "**" if r["pass"] else ""
                cells.append(f"{mark}{error}{mark} / {r['repeatability']:.2f} / {r['matching_score']:.2f}")
                if r["pass"]:
                    handled.append(pair)
            name = method if method in ("sift", "surf", "orb", "akaze", "brisk") else f"{method} + sift"
            lines.append(f"| {name} | {kp} | " + " | ".join(cells) + f" | {', '.join(handled) or 'none'} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--accuracy", action="store_true", help="also evaluate every detector (slow)")
    parser.add_argument("--methods", help="comma-separated detectors for --accuracy (default: all available)")
    parser.add_argument("--markdown", type=Path, help="write the accuracy table to this Markdown file")
    args = parser.parse_args()
    figures: dict = timing(args.repeat)
    if args.accuracy:
        figures.update(surf_against_sift())
        methods = args.methods.split(",") if args.methods else [m for m in METHODS if available(m)]
        rows = evaluate(methods)
        figures["accuracy"] = rows
        for method in methods:
            passed = [f"{r['sequence']} {r['pair']}" for r in rows if r["method"] == method and r["pass"]]
            figures[f"{method}_pairs_within_{PASS_PX:g}px"] = len(passed)
        if args.markdown:
            table = markdown(rows)
            text = args.markdown.read_text() if args.markdown.exists() else ""
            start, end = "<!-- accuracy table: begin -->", "<!-- accuracy table: end -->"
            block = f"{start}\n{table}\n{end}"
            text = text[:text.index(start)] + block + text[text.index(end) + len(end):] if start in text else \
                text + "\n" + block + "\n"
            args.markdown.write_text(text)
            print(f"wrote {args.markdown}")
    report.write("features", {k: v for k, v in figures.items() if k != "accuracy"})
    if args.accuracy:
        path = report.RESULTS / "features_accuracy.json"
        write_json(path, figures["accuracy"], indent=1, replace=True)
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
