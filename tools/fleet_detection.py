"""How well ``canrls fleet`` finds wear on simulated fleets: recall, false alerts, naming.

    .venv/bin/python tools/fleet_detection.py --seeds 1-5            # 50 drives x 10 x 3 s each
    .venv/bin/python tools/fleet_detection.py --seeds 1-3 --duration 6 --workers 2

For each seed: ``canrls.sim.fleet_plan`` writes the fleet, :func:`canrls.fleet.ingest.ingest`
fits it into a SQLite history (in this process, or on a LocalCluster with
``--workers``) with the candidate ranking around residual changes (``rank="auto"``),
:func:`canrls.fleet.detect.assess` assesses it, and the alerts are held against the
truth file. Prints per seed and in all: faulty drives alerted (recall), those whose
first alert names the right parameter or effect, healthy drives alerted; and the same
without the between-recording scatter (each recording's sigma alone). Figures go to
docs/fleet.md; nothing is asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
from pathlib import Path
from typing import Any

from canrls.cli.fleet import rank_candidates
from canrls.fleet import detect
from canrls.fleet.cluster import dask_client
from canrls.fleet.history import History
from canrls.fleet.ingest import JobConfig, ingest
from canrls.fleet.sources import from_manifest
from canrls.sim.fleet_plan import FLEET_EFFECTS, FLEET_KT, make_fleet, write_fleet


def seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def score(fa: detect.FleetAssessment, truth: dict[str, Any]) -> dict[str, Any]:
    faulty = [d for d, t in truth.items() if t["class"] != "healthy"]
    healthy = [d for d, t in truth.items() if t["class"] == "healthy"]
    found, right, by_class = [], [], {}
    for d in faulty:
        t = truth[d]
        a = fa.drive(d).headline
        ok = a is not None and ((a.kind == "new effect" and a.effect == t["effect"])
                                if t["class"] == "harmonic" else a.series == t["parameter"])
        c = by_class.setdefault(t["class"], [0, 0, 0])
        c[0] += 1
        if a is not None:
            found.append(d)
            c[1] += 1
        if ok:
            right.append(d)
            c[2] += 1
    false = [d for d in healthy if fa.drive(d).alerts]
    return {"faulty": len(faulty), "found": len(found), "right": len(right),
            "healthy": len(healthy), "false": false, "by_class": by_class}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-5")
    ap.add_argument("--drives", type=int, default=50)
    ap.add_argument("--recordings", type=int, default=10)
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--workers", type=int, default=0)
    args = ap.parse_args()
    cfg = JobConfig(effects=FLEET_EFFECTS, kt=FLEET_KT)
    total = {"faulty": 0, "found": 0, "right": 0, "healthy": 0, "false": 0, "false_tau0": 0}
    classes: dict[str, list[int]] = {}
    with contextlib.ExitStack() as stack:
        client = stack.enter_context(dask_client(None, args.workers)) if args.workers else None
        for seed in seeds(args.seeds):
            with tempfile.TemporaryDirectory(prefix="canrls-fleet-") as tmp:
                plan = make_fleet(args.drives, args.recordings, args.duration, seed=seed)
                root = write_fleet(plan, Path(tmp) / "fleet")
                truth = plan.truth()["drives"]
                with History.open(Path(tmp) / "h.db") as h:
                    s = ingest(from_manifest(root / "manifest.csv"), cfg, h, client=client,
                               rank="auto", ranker=rank_candidates, max_order=16)
                    recs = h.recordings()
            r = score(detect.assess(recs), truth)
            orig = detect.estimate_tau, detect._own_tau
            detect.estimate_tau = lambda pairs, quantile=0.5: 0.0  # type: ignore[assignment]
            detect._own_tau = lambda pairs: 0.0  # type: ignore[assignment]
            try:  # sigma alone, and no size that matters
                r0 = score(detect.assess(recs, settings=detect.DetectionSettings(
                    min_times_usual=1e-9, min_change={k: 0.0 for k in detect.MIN_CHANGE})),
                    truth)
            finally:
                detect.estimate_tau, detect._own_tau = orig  # type: ignore[assignment]
            for k in ("faulty", "found", "right", "healthy"):
                total[k] += r[k]
            total["false"] += len(r["false"])
            total["false_tau0"] += len(r0["false"])
            for c, v in r["by_class"].items():
                acc = classes.setdefault(c, [0, 0, 0])
                for i in range(3):
                    acc[i] += v[i]
            print(f"seed {seed}: {s.stored} recordings ({s.ranked} ranked); faulty "
                  f"{r['found']}/{r['faulty']} alerted, {r['right']} named right; healthy "
                  f"alerted {len(r['false'])}/{r['healthy']} {r['false'] or ''}; with sigma "
                  f"alone {len(r0['false'])}/{r['healthy']}", flush=True)
    print(f"\nall: recall {total['found']}/{total['faulty']} "
          f"({100 * total['found'] / max(1, total['faulty']):.1f} %), named right "
          f"{total['right']}/{total['found']}, false alerts {total['false']}/{total['healthy']} "
          f"({100 * total['false'] / max(1, total['healthy']):.2f} %); with sigma alone "
          f"{total['false_tau0']}/{total['healthy']} "
          f"({100 * total['false_tau0'] / max(1, total['healthy']):.0f} %)")
    for c, (n, f, ok) in sorted(classes.items()):
        print(f"  {c:9s} {f}/{n} alerted, {ok} named right")


if __name__ == "__main__":
    main()
