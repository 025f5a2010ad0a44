"""stage.dynamic.heads: the shared trunk beside the paper's one MLP per parameter. Shapes and zero deltas at the
start, the warm-up's image at step 0, a killed run that resumes to the same result, the selection's switch, and
one clear error for a networks.pt of the other variant."""

from __future__ import annotations

import dataclasses
import io
import json

import pytest
import torch

from avatar.nets.mlp import DeltaHeads, SharedDeltaHeads, delta_heads
from avatar.representations.bound.dynamic_model import DynamicModelConfig
from avatar.representations.bound.representation import architecture_record, load_dynamic, write_bound_gaussians
from avatar.representations.bound.stage_two import DynamicTrainConfig, train_dynamic
from avatar.representations.bound.warmup import render_frame
from avatar.training.rendering import rasterize
from avatar.training.selection import switch_off
from data_schemas.tables import SchemaError
from tests.representations.bound.conftest import FAR, NEAR, TINY, Scene

SHARED = dataclasses.replace(TINY, heads="shared")
OUTPUTS = {"mu": 3, "s": 3, "q": 4}


def test_shared_heads_give_every_parameter_its_columns_and_start_at_zero() -> None:
    heads = delta_heads("shared", OUTPUTS, point_dim=7, frame_dim=5, width=16, depth=3)
    assert isinstance(heads, SharedDeltaHeads)
    out = heads(torch.randn(11, 7), torch.randn(5))
    assert {k: tuple(v.shape) for k, v in out.items()} == {"mu": (11, 3), "s": (11, 3), "q": (11, 4)}
    assert all(torch.equal(v, torch.zeros_like(v)) for v in out.values())
    # one trunk: a third of the per-parameter heads' weights (the input, hidden and skip layers once, not thrice)
    per_parameter = delta_heads("per_parameter", OUTPUTS, point_dim=7, frame_dim=5, width=16, depth=3)
    assert isinstance(per_parameter, DeltaHeads)
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert count(heads) < 0.4 * count(per_parameter)
    with pytest.raises(ValueError, match="heads=wide: must be one of per_parameter, shared"):
        delta_heads("wide", OUTPUTS, 7, 5, 16, 3)


def test_each_parameter_reads_its_own_columns_of_the_last_layer() -> None:
    heads = SharedDeltaHeads(OUTPUTS, point_dim=4, frame_dim=2, width=8, depth=2)
    point, frame = torch.randn(6, 4), torch.randn(2)
    with torch.no_grad():
        heads.trunk.output.weight.normal_()
        heads.trunk.output.bias.normal_()
    whole = heads.trunk(point, frame)
    out = heads(point, frame)
    assert torch.equal(out["mu"], whole[:, :3]) and torch.equal(out["s"], whole[:, 3:6])
    assert torch.equal(out["q"], whole[:, 6:])
    switch_off([heads])
    assert all(torch.equal(v, torch.zeros_like(v)) for v in heads(point, frame).values())


def test_the_config_check_names_an_unknown_variant() -> None:
    assert DynamicModelConfig(heads="shared").problems() == []
    assert any(p.startswith("heads=wide: must be one of") for p in DynamicModelConfig(heads="wide").problems())


def test_at_step_zero_the_shared_variant_renders_the_warmup_model_exactly(scene: Scene) -> None:
    model = scene.model(SHARED)
    for frame in (NEAR, FAR):
        with torch.no_grad():
            static, _ = render_frame(model.gaussians, scene.meshes, scene.views, frame, 0, "torch")
            dynamic = rasterize(model(scene.cond.frame(frame), scene.meshes.vertices[frame]), scene.views, 0, "torch")
        assert torch.equal(static.rgb, dynamic.rgb) and torch.equal(static.alpha, dynamic.alpha)


def test_a_killed_shared_run_resumes_to_the_same_result(scene: Scene, tmp_path) -> None:
    cfg = DynamicTrainConfig(steps=4, backend="auto", patch_weight=0.0, log_every=1, checkpoint_every=2)
    contact = torch.tensor([True, False]).numpy()
    straight = scene.model(SHARED)
    log = train_dynamic(straight, scene.views, scene.meshes, scene.cond, contact, cfg).log

    class Kill(Exception):
        pass

    def killed_after_two(steps):
        for step in steps:
            if step == 3:
                raise Kill
            yield step

    with pytest.raises(Kill):
        train_dynamic(
            scene.model(SHARED), scene.views, scene.meshes, scene.cond, contact, cfg, tmp_path, killed_after_two
        )
    resumed = scene.model(SHARED)
    result = train_dynamic(resumed, scene.views, scene.meshes, scene.cond, contact, cfg, tmp_path)
    for (name, a), (_, b) in zip(straight.state_dict().items(), resumed.state_dict().items(), strict=True):
        assert torch.equal(a, b), name
    assert [r.loss for r in result.log] == [r.loss for r in log]
    assert any(torch.count_nonzero(p) for n, p in resumed.named_parameters() if n.endswith("trunk.output.weight"))


def _write_model(scene: Scene, folder, trained: DynamicModelConfig, recorded: DynamicModelConfig) -> None:
    """A dynamic stage's folder with the networks of ``trained`` and a model.json that says ``recorded``."""
    model = scene.model(trained)
    folder.mkdir()
    write_bound_gaussians(folder / "gaussians.parquet", model.gaussians, scene.meshes.part_names)
    buffer = io.BytesIO()
    torch.save(model.network_state(), buffer)
    (folder / "networks.pt").write_bytes(buffer.getvalue())
    info = {
        "architecture": architecture_record(recorded),
        "part_names": list(scene.meshes.part_names),
        "num_face_vertices": scene.num_face_vertices,
        "frame_dims": {"hand_pose": scene.cond.hand_pose.shape[1], "expression": scene.cond.expression.shape[1]},
    }
    (folder / "model.json").write_text(json.dumps(info, default=list))


def test_model_json_names_the_variant_and_a_mismatched_networks_file_is_one_clear_error(scene: Scene, tmp_path) -> None:
    assert "heads" not in architecture_record(TINY)  # the paper's variant: model.json as before the setting
    assert architecture_record(SHARED)["heads"] == "shared"
    _write_model(scene, tmp_path / "shared", SHARED, SHARED)
    assert load_dynamic(tmp_path / "shared").cfg.heads == "shared"
    _write_model(scene, tmp_path / "mixed", TINY, SHARED)
    with pytest.raises(SchemaError, match="holds heads=per_parameter networks, but model.json says heads=shared"):
        load_dynamic(tmp_path / "mixed")
    _write_model(scene, tmp_path / "mixed_back", SHARED, TINY)
    with pytest.raises(SchemaError, match="holds heads=shared networks, but model.json says heads=per_parameter"):
        load_dynamic(tmp_path / "mixed_back")
