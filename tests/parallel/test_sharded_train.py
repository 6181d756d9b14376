"""The train step over many devices (`rvggt_jax.train.sharded`, issue 25 item 4) against
`make_train_step` on one device, on 4 host CPU devices: one layout with every split at
once (one compiled step: the suite's time): the scenes over "data" (2), each scene's
frames around a ring of 2 ("frames"), the parameters and optimiser state split 4 ways
(FSDP). Without FSDP the same program shapes run with the state replicated; the layouts
that choose it are checked below without devices. The checks run in tests/helpers/sharded_worker.py
(`train_steps`: the device count is fixed when JAX starts); this file asserts on its
report. The refused layouts and the CLI's parsing need no devices: they run here.

Tolerance 1e-5 relative (float32): the split changes summation order only. The update
(params after - before) is compared where the gradient is above AdamW's noise floor, as
in tests/train/test_accumulate.py (AdamW's first step is lr g / (|g| + 1e-8): where |g|
is ~1e-9, rounding moves it by a fraction of lr, in two correct runs alike); the
gradient (AdamW's first moment / 0.1) everywhere."""

import json

import pytest

from tests.helpers.sharded import sharded_worker_result

TOL = 1e-5
MODES = ("data_frames_fsdp",)


@pytest.fixture(scope="module")
def report():
    code, out, err = sharded_worker_result()  # (started by conftest when the session began)
    assert code == 0, err[-4000:]
    return json.loads(out.strip().splitlines()[-1])["train_steps"]


@pytest.mark.parametrize("mode", MODES)
def test_sharded_step_equals_one_device(report, mode):
    run = report[mode]
    assert run["step"] == 1
    bad = {k: e for k, e in run["metrics"].items() if not e <= TOL}
    assert not bad, (mode, bad)
    assert {"loss_objective", "loss_camera", "loss_conf_depth", "grad_norm"} <= set(run["metrics"])
    assert run["grad"] <= TOL, (mode, run["grad"])
    assert run["params"] <= TOL, (mode, run["params"])
    assert run["update"] <= TOL, (mode, run["update"])  # (in units of the learning rate)


def test_meshes(report):
    assert report["data_frames_fsdp"]["mesh"] == {"data": 2, "frames": 2}


def test_fsdp_splits_the_state(report):
    # every parameter and AdamW moment of the micro layout has a dimension 4 divides;
    # the step counters (scalars) stay replicated
    run = report["data_frames_fsdp"]
    assert run["split_leaves"] >= 0.9 * run["leaves"], run


def test_refused_layouts_say_what_would_work(report):
    refused = report["refused"]
    assert "does not divide the batch" in refused["batch"]
    assert "--frames-per-device 1 (data 1 x frames 4) or 2 (data 2 x frames 2)" in refused["batch"]
    assert "--devices 1 or 2" in refused["batch"] and "--batch a multiple of 4" in refused["batch"]
    assert "must divide --frames 4" in refused["frames"] and "[1, 2, 4]" in refused["frames"]
    assert "there are 4 device(s)" in refused["too_many"]


# ---- no devices needed ------------------------------------------------------------------


def test_layouts():
    from rvggt_jax.train.sharded import TrainLayout, leaf_spec, train_layout
    from jax.sharding import PartitionSpec as P

    assert train_layout(8, 8, 4, available=8) == TrainLayout(8, 1)  # default: every scene on one device
    assert train_layout(8, 4, 16, 8, available=8) == TrainLayout(4, 2)
    assert train_layout(8, 1, 16, 2, fsdp=True, available=8) == TrainLayout(1, 8, True)
    assert train_layout(4, 8, 4, accumulate=2, available=4) == TrainLayout(4, 1)
    assert train_layout(4, 8, 4, available=4).describe() == "4 devices: mesh data 4 x frames 1; parameters replicated"
    # FSDP splits the largest dimension the device count divides
    assert leaf_spec((3, 64, 128), 4) == P(None, None, ("data", "frames"))
    assert leaf_spec((12, 6), 4) == P(("data", "frames"))
    assert leaf_spec((3,), 4) == P() and leaf_spec((), 4) == P()


@pytest.mark.parametrize("args, message", [
    ((4, 6, 4, None), r"--devices 4 does not divide the batch.*there are 6\. Would work: --frames-per-device 1 "
                      r"\(data 1 x frames 4\) or 2 \(data 2 x frames 2\); --devices 1 or 2 or 3 or 6 \(at "
                      r"--frames-per-device 4\); --batch a multiple of 4 \(4, 8, 12, \.\.\.\)"),
    ((8, 2, 6, 3), r"--devices 8 does not divide the batch: 2 device\(s\) per scene leave 4 on axis \"data\", "
                   r"which needs a multiple of 4 scenes per batch \(--batch\); there are 2\. Would work: "
                   r"--devices 2 or 4 \(at --frames-per-device 3\); --batch a multiple of 4"),
    ((6, 2, 4, 1), r"--devices 6 is not a multiple of the 4 devices that share each scene's frames \(--frames 4 / "
                   r"--frames-per-device 1\)\. Would work: --devices 4 or 8 \(at --frames-per-device 1\)$"),
    ((4, 4, 4, 3), r"--frames-per-device 3 must divide --frames 4.*\[1, 2, 4\]"),
])
def test_bad_device_counts_say_what_would(args, message):
    from rvggt_jax.errors import InputError
    from rvggt_jax.train.sharded import train_layout

    with pytest.raises(InputError, match=message):
        train_layout(*args, available=8)


def test_bad_accumulate_with_devices():
    from rvggt_jax.errors import InputError
    from rvggt_jax.train.sharded import train_layout

    # 8 scenes in 4 micro-batches of 2: 4 devices on "data" do not divide them
    with pytest.raises(InputError, match=r"multiple of 4 scenes per micro-batch.*--batch a multiple of 16"):
        train_layout(4, 8, 4, accumulate=4, available=4)


def test_finetune_refuses_devices_that_do_not_divide_the_batch(tmp_path):
    # before any data is read or model loaded (one device is enough)
    from rvggt_jax import train
    from rvggt_jax.errors import InputError

    opts = train.FinetuneOptions(batch=3, frames=4, devices=4)
    with pytest.raises(InputError, match=r"--devices 4 does not divide the batch.*Would work: --frames-per-device 1 "
                                         r"\(data 1 x frames 4\); --devices 1 \(at --frames-per-device 4\); "
                                         r"--batch a multiple of 4"):
        train.finetune(tmp_path, tmp_path / "out", {}, None, opts)


def test_finetune_cli_devices():
    from rvggt_jax.app.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["finetune", "d", "--out", "o", "--devices", "8", "--frames-per-device", "4", "--fsdp"])
    assert (args.devices, args.frames_per_device, args.fsdp) == (8, 4, True)
    args = parser.parse_args(["finetune", "d", "--out", "o"])
    assert (args.devices, args.frames_per_device, args.fsdp) == (1, None, False)
    sub = next(a for a in parser._subparsers._group_actions[0].choices.items() if a[0] == "finetune")[1]
    text = " ".join(sub.format_help().split())
    assert 'mesh axes "data" x "frames"' in text, text


def test_finetune_cli_bad_devices_is_one_line(tmp_path, capsys):
    from rvggt_jax.app.cli import main

    # (before the model loads: neither --weights nor --config is needed to be told)
    assert main(["finetune", str(tmp_path), "--out", str(tmp_path / "o"), "--devices", "2", "--batch", "3"]) == 1
    err = capsys.readouterr().err
    assert "--devices 2 does not divide the batch" in err and "--batch a multiple of 2" in err, err
    assert len(err.strip().splitlines()) == 1, err


def test_a_frame_split_needs_one_frame_count():
    """`rvggt finetune --frames 2-8 --frames-per-device K`: the frame axis would change
    size between buckets, so it is refused naming the fix; without a frame split a range
    is fine (the scenes go over the devices)."""
    from rvggt_jax.errors import InputError
    from rvggt_jax.train.loop import FinetuneOptions, device_layout
    from rvggt_jax.train.sharded import TrainLayout

    with pytest.raises(InputError, match=r"--frames-per-device splits a fixed frame count.*\[2, 4, 8\].*--frames N"):
        device_layout(FinetuneOptions(frames=(2, 8), batch=2, devices=2, frames_per_device=1))
    assert device_layout(FinetuneOptions(frames=(2, 8), batch=2, fsdp=True)) == TrainLayout(1, 1, True)
    assert device_layout(FinetuneOptions(frames=(2, 8), batch=2)) is None
