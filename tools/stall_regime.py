#!/usr/bin/env python3
"""Whether a `bench --compare` run's stall excess comes from error updates or from a
slower error run overall.

Reads DIR/trace.json (the GPU spans of every run's frames: "error", "ceiling" twice) and
prints, for the error run against the first ceiling run and for the second ceiling run
against the first (the noise between identical runs), the median ratio of frame GPU
durations and how many frames are over 25 % slower; then the error run's largest excesses
and whether an error pass ran on the GPU since the frame before (on a shared queue the
passes run between frames, so they add to the frame time, not to a frame's GPU span). A
run whose frames' own GPU spans are slower throughout, those with no pass before them
included, lost its time to something other than the updates.

Usage: tools/stall_regime.py DIR [DIR...]   (DIR: a `bench --compare` output directory)
"""
import json
import signal
import statistics
import sys


def spans(events, name):
    return [e for e in events if e.get("ph") == "X" and e.get("name") == name and "dur" in e]


def main(dirs):
    if not dirs:
        sys.exit(__doc__)
    for d in dirs:
        try:
            with open(f"{d}/trace.json") as f:
                trace = json.load(f)
        except (OSError, ValueError) as e:
            sys.exit(f"{d}/trace.json: {e}")
        events = trace["traceEvents"] if isinstance(trace, dict) else trace
        # GPU spans are on the GPU track: the same name on the draw thread is the CPU side.
        gpu_tids = {e["tid"] for e in spans(events, "error passes")}
        frames = lambda name: [e for e in spans(events, name) if e["tid"] in gpu_tids or not gpu_tids]
        error, ceiling = frames("error"), frames("ceiling")
        passes = spans(events, "error passes")
        n = len(error)
        if n == 0 or len(ceiling) != 2 * n:
            sys.exit(f"{d}: {n} error frames and {len(ceiling)} ceiling frames (want twice as many): not a --compare trace with GPU spans")
        c1, c2 = ceiling[:n], ceiling[n:]
        for label, a, b in (("error / ceiling 1", error, c1), ("ceiling 2 / ceiling 1", c2, c1)):
            ratios = [x["dur"] / max(y["dur"], 1) for x, y in zip(a, b, strict=True)]
            slow = sum(r > 1.25 for r in ratios)
            print(f"{d}: {label}: median GPU frame ratio {statistics.median(ratios):.2f}, {slow} of {n} frames over 1.25")
        excess = sorted(((x["dur"] - y["dur"]) / 1e3, i) for i, (x, y) in enumerate(zip(error, c1, strict=True)))
        for ms, i in reversed(excess[-3:]):
            f = error[i]
            since = error[i - 1]["ts"] + error[i - 1]["dur"] if i > 0 else f["ts"] - 1e9
            near = any(since <= p["ts"] + p["dur"] and p["ts"] < f["ts"] + f["dur"] for p in passes)
            print(f"  frame {i}: GPU span {ms:+.1f} ms over the ceiling's, an error pass since the frame before: {'yes' if near else 'no'}")


if __name__ == "__main__":
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)  # quiet under `| head`
    main(sys.argv[1:])
