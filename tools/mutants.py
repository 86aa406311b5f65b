"""The mutants of ``tools/mutation_check.py``: small breaks of SCALAR-NeRF's core, each with the fast tests that
claim to cover it (standard library only; nothing here runs anything).

Every break is one a user would notice (a wrong image, a wrong split, a wrong block, memory that grows with K, a
run planned too long), not an equivalent rewrite, and every ``old`` snippet occurs exactly once in its file
(``python tools/mutation_check.py --dry-run`` checks it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple


@dataclass(frozen=True, kw_only=True)
class Mutant:
    """One small break of the method's core and the tests that must catch it.

    Attributes:
        name: short identifier (``--only``).
        path: the mutated file, relative to the repository root (a .py file under scalar_nerfstudio/).
        old: a snippet occurring exactly once in the file.
        new: what replaces it (the break).
        why: one line: what the break does to the method.
        tests: pytest node ids (``tests/test_x.py::test_y``) or ``-k EXPRESSION`` selections that claim to cover it.
        slow: the tests are marked slow (then ``-m "not slow"`` is not added).
    """

    name: str
    path: str
    old: str
    new: str
    why: str
    tests: Tuple[str, ...]
    slow: bool = False


def node_ids(test_file: str, *names: str) -> Tuple[str, ...]:
    """``tests/test_<test_file>.py::<name>`` for each of ``names``."""
    return tuple(f"tests/test_{test_file}.py::{name}" for name in names)


FUSION, BLOCKS, MODELS = "scalar_nerfstudio/fusion/", "scalar_nerfstudio/blocks/", "scalar_nerfstudio/models/"
PARTS = "scalar_nerfstudio/model_components/"
GUARD_SCENE = node_ids(
    "block_selection", "test_nearest_guarded_gives_the_global_model_where_the_nearest_block_learnt_nothing",
)
GUARD_TESTS = node_ids(
    "fusion",
    "test_nearest_guarded_gives_the_global_model_where_the_block_is_transparent_and_it_is_opaque",
    "test_guard_transparent_on_missing_and_extreme_values",
) + GUARD_SCENE
BLOCK_COPY = node_ids("block_selection", "test_a_block_started_from_the_global_model_renders_as_the_global_model")
SURFACE_SCENE = "test_surface_rule_renders_one_block_per_ray_and_matches_rendering_every_block"
NEAREST_IDW_SCENE = "test_nearest_idw_renders_the_two_nearest_blocks_per_ray_and_matches_blending_every_block"
STORY = node_ids(
    "method_story", "test_the_default_fusion_beats_its_own_global_model",
    "test_the_fused_images_are_the_blocks_not_the_global_models",
)
SELECT_RAYS = "test_select_rays_reads_the_global_depth_only_for_the_rules_that_need_it"

MUTANTS: Tuple[Mutant, ...] = (
    # ------------------------------------------------------------------------------------------ fusion rules
    Mutant(
        name="nearest-picks-farthest", path=FUSION + "selection.py",
        old="index = torch.argmin(dist, dim=0)", new="index = torch.argmax(dist, dim=0)",
        why="nearest / nearest-guarded take the block whose centre is farthest from the camera",
        tests=node_ids("fusion", "test_nearest_block", "test_fuse_outputs_nearest_block_and_global_only")
        + node_ids("block_selection", "test_nearest_renders_each_ray_once"),
    ),
    Mutant(
        name="guard-never-fires", path=FUSION + "rules.py",
        old="    return torch.where((transparent & opaque)[None], torch.zeros_like(weights), weights)",
        new="    return weights",
        why="nearest-guarded never gives a transparent block's pixels to the opaque global model",
        tests=GUARD_TESTS,
    ),
    Mutant(
        name="guard-always-fires", path=FUSION + "rules.py",
        old="torch.where((transparent & opaque)[None],", new="torch.where(opaque[None],",
        why="nearest-guarded shows the global model wherever it is opaque: the blocks' detail never shows",
        tests=GUARD_TESTS,
    ),
    Mutant(
        name="idw-exponent-sign", path=FUSION + "numerics.py",
        old="torch.exp(-gamma * torch.log(ratio))", new="torch.exp(gamma * torch.log(ratio))",
        why="idw, nearest-idw and surface weight far blocks more than near ones (d^+gamma)",
        tests=node_ids(
            "fusion", "test_idw_weights_sum_to_one_and_inverse_distance",
            "test_nearest_idw_weights_blend_the_nearest_blocks_by_inverse_distance",
            "test_fuse_outputs_idw_uses_same_weights",
        ) + node_ids("block_selection", "test_score_weights_favour_the_block_holding_the_point"),
    ),
    Mutant(
        name="global-picks-farthest-colour", path=FUSION + "rules.py",
        old="winner = torch.argmin(dist, dim=0)", new="winner = torch.argmax(dist, dim=0)",
        why="the paper's global rule takes the block colour farthest from the global model's",
        tests=node_ids(
            "fusion", "test_global_matches_brute_force", "test_global_hand_made_and_ties",
            "test_fuse_outputs_global_depth_follows_colour_winner",
        ) + node_ids("block_selection", "test_global_rule_over_chosen_blocks_and_over_every_block"),
    ),
    Mutant(
        name="blend-not-normalised", path=FUSION + "blend.py",
        old="    shares = scaled / scaled.sum(dim=0).clamp_min(1.0)", new="    shares = scaled",
        why="blended weights sum above 1: idw / nearest-idw / surface pixels too bright where blocks mix",
        tests=node_ids("fusion", "test_fuse_weighted_ignores_nonfinite", "test_fuse_outputs_idw_uses_same_weights")
        + node_ids("block_selection", NEAREST_IDW_SCENE),
    ),
    Mutant(
        name="selection-keeps-worst", path=FUSION + "selection.py",
        old=".indices[:blocks_per_ray]", new=".indices[-blocks_per_ray:]",
        why="blocks_per_ray keeps the worst-scoring (farthest) blocks: surface, global, nearest-idw use wrong ones",
        tests=node_ids(
            "block_selection", "test_select_blocks_keeps_the_lowest_scores_per_pixel",
            "test_surface_fusion_takes_the_block_holding_the_surface_and_never_a_missing_one", SURFACE_SCENE,
        ) + node_ids("fusion", "test_nearest_blocks_marks_the_nearest_valid_blocks"),
    ),
    # ------------------------------------------------------------------------------------------ the split
    Mutant(
        name="split-scale-ignored", path=BLOCKS + "split.py",
        old="scale_arr = np.asarray(scale, dtype=np.float64)", new="scale_arr = np.ones(3)",
        why="s_AABB is ignored: each block is its KMeans group's bare camera box, without the overlap margin",
        tests=node_ids(
            "block_split", "test_scale_matches_alg1_diagonal_formula",
            "test_thin_block_on_split_axis_is_widened_not_whole_layout", "test_per_axis_scale_only_grows_x",
        ),
    ),
    Mutant(
        name="split-no-regroup", path=BLOCKS + "split.py",
        old="inside = np.all((centres >= lo) & (centres <= hi), axis=1)",
        new="inside = np.zeros(centres.shape[0], dtype=bool)",
        why="images are not regrouped into the scaled boxes: blocks are the disjoint KMeans groups, no overlap",
        tests=node_ids(
            "block_split", "test_exactly_planar_layout_keeps_flat_axis_and_overlaps", "test_collinear_layout",
            "test_castle_cover_overlap_superset_deterministic",
        ),
    ),
    Mutant(
        name="split-kmeans-on-x", path=BLOCKS + "split.py",
        old="labels = kmeans.fit_predict(centres)", new="labels = kmeans.fit_predict(centres[:, :1])",
        why="KMeans clusters the camera centres on x alone: cameras apart in y end up in one block",
        tests=node_ids(
            "block_split", "test_single_camera_groups_stay_small",
            "test_thin_block_on_split_axis_is_widened_not_whole_layout",
        ),
    ),
    # ------------------------------------------------------------------------------------------ automatic K, capacity
    Mutant(
        name="capacity-k-from-width", path=BLOCKS + "capacity.py",
        old="math.ceil(pixels * pixels / float(1 << log2_hashmap_size))",
        new="math.ceil(pixels / float(1 << log2_hashmap_size))",
        why="automatic K from the layout's width in pixels, not its area (R / T): large captures get one block",
        tests=node_ids(
            "capacity", "test_object_capture_at_very_high_resolution_is_split",
            "test_spread_capture_gets_several_blocks_and_more_with_resolution",
        ),
    ),
    Mutant(
        name="capacity-table-uncapped", path=BLOCKS + "capacity.py",
        old="cells = max(min(pixels * pixels, float(block_pixels)), 2.0)", new="cells = max(pixels * pixels, 2.0)",
        why="a block's table is sized by its extent alone, not capped by its images' pixels (rows never filled)",
        tests=node_ids("capacity", "test_block_capacity_grows_with_extent_and_is_capped_by_pixels"),
    ),
    # ------------------------------------------------------------------------------------------ how a block starts
    Mutant(
        name="start-table-not-copied", path=MODELS + "block_start.py",
        old="        model.field.encoder.load_state_dict(global_model.field.encoder.state_dict())", new="        pass",
        why="block_init global: a block starts from a fresh hash table instead of a copy of the global model's",
        tests=BLOCK_COPY,
    ),
    Mutant(
        name="start-wrong-embeddings", path=MODELS + "block_start.py",
        old="global_model.field.appearance.weight[rows]", new="global_model.field.appearance.weight[: len(rows)]",
        why="a block copies the appearance embeddings of the first images, not those of its own images",
        tests=BLOCK_COPY,
    ),
    Mutant(
        name="start-decoder-not-copied", path=MODELS + "block_start.py",
        old='if decoder_mode != "independent":', new='if decoder_mode == "independent":',
        why="finetune / frozen blocks start from a fresh decoder (and independent ones from the global one)",
        tests=node_ids("blocks", "test_block_starts_from_global_decoder_and_only_its_images") + BLOCK_COPY,
    ),
    Mutant(
        name="store-unbounded", path=MODELS + "block_store.py",
        old="for other in self.resident.over_limit(keep=block):",
        new="for other in self.resident.over_limit(keep=block)[:0]:",
        why="blocks loaded from their files are never released: max_resident_blocks ignored, memory grows with K",
        tests=node_ids(
            "block_memory",
            "test_block_store_keeps_weights_in_files_loads_them_back_bounded_and_never_loses_a_trained_block",
            "test_rendering_loads_blocks_from_their_files_bounded_and_gives_the_same_image",
        ),
    ),
    # ------------------------------------------------------------------------------------------ block per ray
    Mutant(
        name="selection-ignores-observation", path=MODELS + "block_selection.py",
        old="    if regions.observation is not None:\n        usable = observed_at(",
        new="    if False:\n        usable = observed_at(",
        why="observed_blocks_only is ignored: rays take blocks whose cameras never saw the surface point",
        tests=node_ids(
            "block_selection", SELECT_RAYS,
            "test_only_blocks_whose_cameras_observe_the_surface_are_chosen_and_unobserved_rays_are_global",
        ),
    ),
    Mutant(
        name="selection-centres-by-position", path=MODELS + "block_selection.py",
        old="centres = regions.centres[block_ids].to(origins.device)",
        new="centres = regions.centres[: len(block_ids)].to(origins.device)",
        why="block centres taken by position, not by id: a partly trained run scores rays against the wrong blocks",
        tests=node_ids("block_selection", SELECT_RAYS),
    ),
    # ------------------------------------------------------------------------------------------ the fused renderer
    Mutant(
        name="guard-renders-wrong-rays", path=MODELS + "fused_render.py",
        old="self._render_global_rays(ray_bundle, suspects, normals)",
        new="self._render_global_rays(ray_bundle, ~suspects, normals)",
        why="nearest-guarded renders the global model on the opaque rays: a block that learnt nothing stays empty",
        tests=GUARD_SCENE,
    ),
    Mutant(
        name="winner-id-shifted", path=MODELS + "fused_render.py",
        old="position_to_id[weights_winner(weights) + 1]", new="position_to_id[weights_winner(weights)]",
        why="block_winner (the winner map, the viewer's block colours) names the wrong block",
        tests=node_ids("block_selection", SURFACE_SCENE, NEAREST_IDW_SCENE),
    ),
    Mutant(
        name="fusion-renders-global-for-blocks", path=MODELS + "fused_render.py",
        old="return self._render_subset(self.block_model(block), ray_bundle, rays, normals, block)",
        new="return self._render_subset(self.global_model, ray_bundle, rays, normals, block)",
        why="the fused renderer draws the global model where a block was chosen: the blocks' training never shows",
        tests=STORY, slow=True,
    ),
    # ------------------------------------------------------------------------------------------ the block phase
    Mutant(
        name="block-table-not-trained", path="scalar_nerfstudio/method_configs.py",
        old='"block_encoder": _adam(4e-2),', new='"block_encoder": _adam(0.0),',
        why="a block's hash table is never updated (learning rate 0): blocks learn only through their decoder",
        tests=STORY, slow=True,
    ),
    Mutant(
        name="one-model-never-restarts", path="scalar_nerfstudio/pipeline.py",
        old="one_model_restart: float = 0.5", new="one_model_restart: float = 0.0",
        why="a run of one model decays once instead of restarting at the blocks' rates: the demo ends 1.4 dB lower",
        tests=node_ids("cli", "test_demo_command_reaches_the_psnr_the_readme_promises"), slow=True,
    ),
    Mutant(
        name="pose-gradient-cut", path="scalar_nerfstudio/models/scalar_model.py",
        old="density, geo = self.field.density_at_unit(kept, encoding=encoding, gradient_rows=rows)",
        new="density, geo = self.field.density_at_unit(kept.detach(), encoding=encoding, gradient_rows=rows)",
        why="pose refinement gets no gradient (the kernels' positions carry none): a wrong pose is never corrected",
        tests=node_ids("pose_refinement", "test_corrections_are_learnt_by_the_global_phase_kept_by_the_blocks_and_bring_a_moved_camera_back"),
        slow=True,
    ),
    Mutant(
        name="blocks-learn-poses", path="scalar_nerfstudio/models/scene_model.py",
        old="learn=block is None)", new="learn=True)",
        why="each block's phase moves the cameras the global model was fitted to, and the next block starts from them",
        tests=node_ids("pose_refinement", "test_corrections_are_learnt_by_the_global_phase_kept_by_the_blocks_and_bring_a_moved_camera_back"),
        slow=True,
    ),
    # ------------------------------------------------------------------------------------------ rendering, sampling
    Mutant(
        name="weights-no-transmittance", path=PARTS + "rendering.py",
        old="weights = (transmittance * alphas).clamp(0.0, 1.0)", new="weights = alphas.clamp(0.0, 1.0)",
        why="a sample's weight ignores the light reaching it: what is behind a surface shows through it",
        tests=node_ids("model_components", "test_volume_rendering_weights_stay_valid"),
    ),
    Mutant(
        name="contraction-unbounded", path="scalar_nerfstudio/fields/scalar_field.py",
        old="(2.0 - inverse) * inverse)", new="(2.0 - inverse))",
        why="the contraction does not divide by the norm of x: far points leave the ball (grids, observation, torch sampling)",
        tests=node_ids("model_components", "test_contraction_matches_mipnerf360_and_stays_in_the_ball")
        + node_ids("block_selection", "test_unit_cube_to_world_inverts_the_contraction"),
    ),
    Mutant(
        name="spacing-inverse-wrong", path=PARTS + "sampling.py",
        old="1.0 / (2.0 * (1.0 - s).clamp_min(1e-6))", new="1.0 / (1.0 - s).clamp_min(1e-6)",
        why="samples beyond 1 unit are placed at twice their distance: the near background gets no samples",
        tests=node_ids("model_components", "test_spacing_round_trip_and_sorted_intervals"),
    ),
    # ------------------------------------------------------------------------------------------ training length
    Mutant(
        name="length-ignores-workers", path=BLOCKS + "length.py",
        old="return math.ceil(num_blocks_trained / max(workers, 1)) if num_blocks_trained > 0 else 0",
        new="return num_blocks_trained",
        why="a time budget plans the blocks one after another, whatever --pipeline.block-workers",
        tests=node_ids("length", "test_blocks_on_workers_get_the_time_of_the_waves"),
    ),
    Mutant(
        name="length-block-total-pixels", path=BLOCKS + "length.py",
        old="mean_block = sum(block_pixels) / len(block_pixels) if block_pixels else 0.0",
        new="mean_block = float(sum(block_pixels))",
        why="block steps planned from all the blocks' pixels together, not one block's: K times too long",
        tests=node_ids("length", "test_the_capture_plans_more_steps_for_more_pixels"),
    ),
)
