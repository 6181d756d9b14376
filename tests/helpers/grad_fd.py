"""Float64 finite-difference check of `jax.grad` through `rvggt_forward`, run as a
subprocess by tests/model/test_grad.py (x64 must be set before JAX starts).

The model computes in float32 by design (norms, softmax and matmul accumulation name
`jnp.float32`), which limits central differences to ~1e-3. To check the *same code* in
float64, this process maps `jnp.float32` to float64 before importing rvggt_jax (every
place the model names float32, its default arguments included) and the aggregator's
compute dtype to float64; parameters and images are float64 too. Nothing in the library
changes. Prints one JSON line {preset: relative error}.

    JAX_ENABLE_X64=1 python tests/helpers/grad_fd.py dense regime
"""

import json
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

jnp.float32 = jnp.float64  # before rvggt_jax is imported (see the docstring)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository (run by path)
from tests.helpers.micro import micro_config  # noqa: E402

import rvggt_jax  # noqa: E402
from rvggt_jax.config import VGGTConfig  # noqa: E402
from rvggt_jax.model.forward import rvggt_forward  # noqa: E402

VGGTConfig.compute_dtype = property(lambda self: jnp.dtype(jnp.float64))


def main(presets):
    config = micro_config(enable_point=False, enable_track=False)
    tree = rvggt_jax.init_params(config, 1)
    treedef = jax.tree.structure(tree)
    host = [np.asarray(x, np.float64) for x in jax.tree.leaves(tree)]
    params = jax.tree.unflatten(treedef, [jnp.asarray(x) for x in host])
    rng = np.random.default_rng(0)
    images = jnp.asarray(rng.random((1, 3, 3, 28, 42)))
    # a random direction in parameter space, scaled like each leaf (so no leaf dominates);
    # the direction, the perturbations and the dot product in float64 numpy on the host
    # (jitted, they were two programs more to compile; eagerly, leaf by leaf, every shape
    # compiled its own ops)
    direction = [rng.standard_normal(x.shape) * (x.std() + 1e-3) for x in host]

    def shifted(s):
        return jax.tree.unflatten(treedef, [jnp.asarray(a + s * d) for a, d in zip(host, direction)])

    def dot(g):
        return sum(float(np.vdot(np.asarray(a, np.float64), d)) for a, d in zip(jax.tree.leaves(g), direction))

    out = {}
    for preset in presets:
        cfg = config.with_compression(preset)

        def loss(p):
            o = rvggt_forward(p, images, cfg)
            # the first camera iteration: later ones see the previous encoding through a
            # stop_gradient (as upstream), which finite differences do not
            return jnp.sum(o["pose_enc_list"][0] ** 2) + jnp.mean(o["depth"][..., 0] * o["depth_conf"])

        # one compiled program for all evaluations (the value of value_and_grad is the loss)
        vg = jax.jit(jax.value_and_grad(loss))
        _, g = vg(params)
        analytic = dot(g)
        # central differences at a step where their truncation error (~eps^2) is far
        # below the target and float64 rounding (~1e-16 / eps) still negligible
        eps = 1e-6
        plus = vg(shifted(eps))[0]
        minus = vg(shifted(-eps))[0]
        numeric = (plus - minus) / (2 * eps)
        out[preset] = {"analytic": float(analytic), "numeric": float(numeric),
                       "rel_err": float(abs(analytic - numeric) / max(abs(numeric), 1e-30))}
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1:] or ["dense", "regime"])
