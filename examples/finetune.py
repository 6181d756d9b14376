"""Fine-tuning example: synthetic scenes written in the training folder layout, then
`rvggt_jax.train.finetune` on them (the same code as `rvggt finetune`). Defaults to the
bundled tiny random-weight model so it runs in minutes on a CPU.

    python examples/finetune.py [--weights CKPT] [--steps 20] [--out finetune_out]

Equivalent CLI once a data folder exists:
    rvggt finetune DATA_DIR --weights CKPT --out finetune_out --steps 20 --frames 4 --size 56x84
"""

import argparse
from pathlib import Path

import rvggt_jax
from rvggt_jax import train
from rvggt_jax.synthetic import make_scene, write_scene

DATA = Path(rvggt_jax.__file__).parent / "examples_data"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=str(DATA / "tiny"), help="checkpoint to fine-tune")
    ap.add_argument("--out", default="finetune_out")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--size", default="56x84", help="HxW, multiples of 14")
    ap.add_argument("--train", default="all", help="all, heads, or comma-separated path prefixes")
    args = ap.parse_args()
    rvggt_jax.prefer_threaded_convolutions()  # CPU: multi-threaded convolutions (before anything starts JAX)

    h, w = (int(v) for v in args.size.split("x"))
    out = Path(args.out)
    data = out / "data"
    if not data.is_dir():  # ray-cast rooms with exact depth and cameras, in the folder layout
        for i in range(args.scenes):
            write_scene(make_scene(frames=2 * args.frames, height=2 * h, width=2 * w, seed=i), "folder", data)
    params, config = rvggt_jax.load_pretrained(args.weights)
    trained = args.train if args.train in ("all", "heads") else tuple(args.train.split(","))
    opts = train.FinetuneOptions(steps=args.steps, frames=args.frames, size=(h, w), learning_rate=1e-4,
                                 warmup_steps=max(1, args.steps // 10), train=trained, log_every=5)
    model_dir = train.finetune(data, out, params, config, opts)
    print(f"done: {model_dir}; log in {out / 'log.jsonl'}")


if __name__ == "__main__":
    main()
