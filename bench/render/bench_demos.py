"""How long building each procedural demo takes, beside its size (the byte budget is a test:
tests/scene/test_demos.py; the time is a figure, as machine load decides it).

    python -m bench.render.bench_demos [--sizes default small] [--repeat 3]

Writes results/bench_demos.json: per demo and size the first build in this process (it
also imports the demo's module, and trimesh for the first demo) and the fastest of
`--repeat`.
"""

from __future__ import annotations

import argparse
import os
import time

from bench.common import RESULTS, add_output_flags, finish, smoke

SECTION = "bench_demos"


def measure(name: str, size: str, repeat: int) -> dict:
    from nprt.scene.demos import make_demo

    walls = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        scene = make_demo(name, size)
        walls.append(time.perf_counter() - t0)
    s = scene.summary()
    return {"demo": name, "size": size, "first_s": round(walls[0], 3),
            "best_s": round(min(walls), 3),
            "instanced_triangles": s["instanced_triangles"], "instances": s["instances"],
            "mesh_mb": round(s["mesh_bytes"] / 1e6, 2)}


def markdown(res: dict) -> str:
    lines = ["| demo | size | first build s | fastest s | instanced triangles | instances "
             "| base meshes MB |", "| --- | --- |" + " ---: |" * 5]
    lines += [f"| {r['demo']} | {r['size']} | {r['first_s']:.2f} | {r['best_s']:.2f} | "
              f"{r['instanced_triangles']:,} | {r['instances']:,} | {r['mesh_mb']:.2f} |"
              for r in res["rows"]]
    return "\n".join(lines)


def main(argv=None) -> int:
    from nprt.scene.demos import DEMOS

    ap = argparse.ArgumentParser(prog="python -m bench.render.bench_demos",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--demos", nargs="+", default=list(DEMOS))
    ap.add_argument("--sizes", nargs="+", default=["default", "small"])
    ap.add_argument("--repeat", type=int, default=3, help="builds per row, the fastest kept")
    add_output_flags(ap, RESULTS)
    args = smoke(ap.parse_args(argv), demos=["forest"], sizes=["tiny"], repeat=1)
    load_before = os.getloadavg()
    rows = [measure(d, z, args.repeat) for z in args.sizes for d in args.demos]
    res = {"args": {k: str(v) for k, v in vars(args).items()}, "load_before": load_before,
           "load_after": os.getloadavg(), "rows": rows}
    intro = ("## Building the demos (`bench_demos.py`)\n\n"
             f"`python -m bench.render.bench_demos` (`{{json}}`): each demo's first build "
             f"and the fastest of {args.repeat}, in one process (load {load_before[0]:.1f} before, "
             f"{res['load_after'][0]:.1f} after).\n\n")
    finish(res, args.out / "bench_demos.json", markdown=markdown, section=SECTION, intro=intro,
           update_readme=not args.no_readme)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
