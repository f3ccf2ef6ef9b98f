"""The teacher's targets averaged over flips and transposes (``train.distill_tta``), on a real render."""
import numpy as np
import pytest
import torch


def test_teacher_views_average_the_outputs_of_the_transformed_frames(render):
    """Two views: the mean of the teacher's output on the frame and, transposed back, on the transposed frame's own
    features (built from the transposed layers, not by the augmentation): the transform and its undoing are right."""
    from kpcn.data import pair_tensors
    from kpcn.inference import load_model
    from kpcn.io.frame import Frame
    from kpcn.train_steps import model_inputs, teacher_outputs

    teacher = load_model("unet_kpcn:wide64h", device="cpu")
    frame = render("test:glossy", spp=4)
    swapped = Frame(layers={k: np.ascontiguousarray(v.swapaxes(0, 1)) for k, v in frame.layers.items()},
                    meta=frame.meta)
    x, xt = (model_inputs(teacher, pair_tensors(f, f)) for f in (frame, swapped))
    with torch.no_grad():
        plain, other = teacher(x), teacher(xt)
        got = teacher_outputs(teacher, x, views=2)
        one = teacher_outputs(teacher, x, views=1)
    for k in ("color", "diffuse", "specular"):
        want = (plain[k] + other[k].transpose(-1, -2)) / 2
        torch.testing.assert_close(got[k], want, rtol=1e-4, atol=1e-5)
        assert torch.equal(one[k], plain[k])
    assert (plain["color"] - other["color"].transpose(-1, -2)).abs().max() > 1e-4  # the views do differ


def test_distill_tta_is_checked():
    from kpcn.config import ConfigError
    from kpcn.train_config import TrainConfig

    for bad in (0, 9, 2.5):
        with pytest.raises(ConfigError, match="distill_tta"):
            TrainConfig(distill_tta=bad)
