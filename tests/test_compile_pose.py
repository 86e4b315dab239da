"""`compile.pose=true` (Avatar.compile_pose_path): the corrector and the deformer under torch.compile render the same
image and give every parameter the same gradient as eager, on the torch code a GPU runs (compiled CPU loops off; on
CUDA with `-m gpu`: Triton's kernels), and the module's parameter names (its checkpoints) do not change. Slow: inductor
compiles for ~30 s on 2 cores."""

from __future__ import annotations

import pytest
import torch
import torch._dynamo
from test_table4_rows import _batch, composed

from framework.runtime import use_compiled_paths


def _module(compile_pose: bool):
    from framework.lightning.module import SplatModule

    torch.manual_seed(0)
    flag = "true" if compile_pose else "false"
    cfg = composed("+experiment=paper_full", "body=procedural", "deformer.grid_resolution=8", "gaussians.num=300",
                   "rasterizer=torch_ref", "stages.stage1_steps=0", f"compile.pose={flag}")  # fmt: skip
    data_info = {"bounds": [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], "num_frames_total": 2, "body_name": "procedural",
                 "num_joints": 17}  # fmt: skip
    return SplatModule(cfg, data_info)


def _step(module, batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    out = module.render_batch(batch, step=3000)  # SH degree 3, both MLPs on
    total, _ = module.loss_fn(out.render, batch, out.aux)
    total.backward()
    grads = {name: p.grad.clone() for name, p in module.named_parameters() if p.grad is not None}
    return out.render.rgb.detach(), grads


NEEDS_CUDA = {"condition": not torch.cuda.is_available(), "reason": "needs a CUDA device"}


@pytest.mark.slow
@pytest.mark.parametrize(
    "device", ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(**NEEDS_CUDA)])]
)
def test_compiled_pose_path_matches_eager(tmp_path, monkeypatch, device: str) -> None:
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))
    batch = _batch(24)
    batch.image.uniform_(0, 1, generator=torch.Generator().manual_seed(1))
    batch.mask[:, 6:18, 6:18] = 1.0
    batch.pose.normal_(0, 0.3, generator=torch.Generator().manual_seed(2))  # a bent pose: polar, stretch, SH frames
    batch = batch.to(device)
    previous = use_compiled_paths(False)  # on a CPU: the torch code a GPU runs
    torch._dynamo.utils.counters.clear()
    try:
        eager, compiled = _module(False).to(device), _module(True).to(device)
        assert compiled.avatar.pose_compiled and not eager.avatar.pose_compiled
        assert list(compiled.state_dict()) == list(eager.state_dict())  # checkpoints keep their keys
        compiled.load_state_dict(eager.state_dict())
        rgb_e, grads_e = _step(eager, batch)
        rgb_c, grads_c = _step(compiled, batch)
    finally:
        use_compiled_paths(previous)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] >= 2  # the corrector's and the deformer's, at least
    assert rgb_e.abs().max() > 0.05  # something was rendered
    torch.testing.assert_close(rgb_c, rgb_e, rtol=0, atol=1e-5)  # fused float32 arithmetic: rounding only
    assert grads_c.keys() == grads_e.keys()
    assert any(".corrector." in n for n in grads_e) and any(".deformer." in n for n in grads_e)  # both MLPs trained
    for name, g in grads_e.items():  # fused kernels reassociate sums: within 1e-4 of each gradient's scale
        torch.testing.assert_close(grads_c[name], g, rtol=0, atol=1e-4 * float(g.abs().max()) + 1e-9, msg=name)
