"""The benchmark's settings and its variant plan: which variants run, in which order, with which configs.

Variants (same scene, same machine, same run; each trains in its own process):

* ``ngp-t`` / ``ngp-t2``: one model (the paper's NGP_T / NGP_{T+2}), ``G + K B`` steps, with the blocks'
  table 2^T / a table 4x as large, 2^(T+2) (``--log2-table T``). Their former names ``ngp19`` /
  ``ngp21`` (after the paper's default T = 19) are accepted everywhere (:data:`VARIANT_ALIASES`).
  They follow the one-model learning-rate schedule of the defaults (``--pipeline.one-model-restart``:
  hold, then restart at a share of the run).
* ``ngp-t-decay`` / ``ngp-t2-decay``: the same one models with one warm-up and decay over the whole run
  (``--pipeline.one-model-restart 0``). The report compares the blocks with the better of the two
  schedules of each table size (:data:`ONE_MODEL_SCHEDULES`).
* ``global``: the SCALAR-NeRF global phase (``G`` steps, table 2^T). The block variants below all
  start from this one trained global model (its time is counted in theirs), as in the paper.
* ``scalar``: the paper's: K fresh blocks (``--pipeline.block-init fresh``) of ``B`` steps each,
  fine-tuned decoders, s_AABB = 1.2, tables 2^T; evaluated
  with ``global`` fusion (SCALAR-NeRF), ``surface``, ``idw``, ``nearest`` and ``global-only`` (the same
  models, other fusions; ``global-only`` is the global model alone).
* ``scalar-init-global``: as ``scalar``, but every block starts as a copy of the global model
  (``--pipeline.block-init global``, the default since it measured best: its frame, table, occupancy
  grid, appearance) and fine-tunes it; evaluated with ``nearest`` first.
* ``scalar-fitted``: as ``scalar`` (own frame, table 2^T), but each block's table is first fitted to the
  global model's encoding on the block's observed space (``--pipeline.block-init fitted``); evaluated
  with ``nearest`` first.
* The ablations below start their blocks fresh, as the paper's.
* ``scalar-wo-sd``: independent decoders (the paper's "w/o SD"); evaluated with ``global`` fusion and
  with ``idw``, which is Block-NeRF's recipe (independent blocks + inverse distance weighting).
* ``scalar-wo-ft``: frozen copies of the global decoder ("w/o FT").
* ``scalar-s1.0``: s_AABB = 1.0 (no overlap beyond KMeans' cells).
* ``scalar-autocap``: K blocks with per-block table size and resolution chosen automatically.
* ``auto``: ``ns-train scalar-nerf``'s defaults: automatic K, blocks as the defaults start them, the
  default fusion first (K = 1 means one model of ``G + K B`` steps).
* ``auto-fitted``: ``auto`` with ``--pipeline.block-init fitted`` (when automatic K > 1).
* ``auto-parallel``: ``auto`` on the equal wall-clock budget with K workers: every block trains
  ``--parallel-block-steps`` steps (default ``K B``, the steps NGP_T trains after the global phase), as
  ``scalar-nerf-train-blocks`` trains them at once on K workers. Evaluated at its end only.
* ``auto-parallel-fitted``: ``auto-parallel`` with ``--pipeline.block-init fitted``.
* ``nerfacto``: nerfstudio's nerfacto, torch implementation, for the wall-clock SCALAR-NeRF took.
  Its LPIPS needs downloaded AlexNet weights, so it is not computed for nerfacto.

``--fusions`` replaces every block variant's list of fusions above (the first is the run's).

Equal budgets: every SCALAR/NGP variant trains ``G + K B`` steps of the same ray batch; nerfacto
trains for the same wall-clock as ``scalar`` (set when the schedule gets to it). The report also
compares at equal wall-clock with K workers: a block variant's time with its blocks trained in
parallel (``G``'s time + its slowest block's) against the NGP curves at that time. The equal-steps
variants do the same total work as NGP_T, so on K workers they finish early; ``auto-parallel`` is the
budget where the K workers buy K times the block steps in NGP_T's wall-clock. When a one-model run
(``ngp-t``, ``ngp-t2`` and their ``-decay`` runs) ends more than :data:`WALL_CLOCK_TOLERANCE` before
the longest such wall-clock, it is trained once more, from the start, for as many steps as fit in
that wall-clock at its first run's pace (``ngp-t-wall-clock``, ``ngp-t-decay-wall-clock``, ...: see
:func:`wall_clock_variants`): a one-model run's learning-rate schedule spans its own steps, so its
curve cannot be read past its end, and its end is not what it reaches in the blocks' time. A run's
pace changes with its length and the machine's state, so when that run
ends more than the tolerance away from the wall-clock, it is planned again from its own pace
(``ngp-t-wall-clock-2``, ...; :func:`wall_clock_retry`), up to ``--wall-clock-tries`` runs, and the
run that ended nearest the wall-clock is the one read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

__all__ = [
    "DECAY_SUFFIX", "ONE_MODEL_SCHEDULES", "ONE_MODEL_VARIANTS", "VARIANTS", "VARIANT_ALIASES", "WALL_CLOCK_SUFFIX", "canonical_variant", "former_variant_name", "WALL_CLOCK_TOLERANCE", "BenchmarkConfig", "Variant", "auto_k", "blocks_wall_clock_s", "check_options",
    "nearest_to_wall_clock", "one_model_schedule", "parallel_block_steps", "plan", "use_quick_budgets", "wall_clock_retry", "wall_clock_variants",
]

#: A one-model variant with one warm-up and decay over its whole run is named ``<variant>DECAY_SUFFIX``.
DECAY_SUFFIX = "-decay"
#: The one-model runs of each table size (NGP_T: the blocks' table 2^T, NGP_{T+2}: a 4x table), by
#: learning-rate schedule: ``restart`` (the one-model default, ``--pipeline.one-model-restart``) and
#: ``decay`` (``--pipeline.one-model-restart 0``).
ONE_MODEL_SCHEDULES: Dict[str, Dict[str, str]] = {
    name: {"restart": name, "decay": name + DECAY_SUFFIX} for name in ("ngp-t", "ngp-t2")
}
#: The one-model variants: every table size with every schedule.
ONE_MODEL_VARIANTS: Tuple[str, ...] = tuple(v for schedules in ONE_MODEL_SCHEDULES.values() for v in schedules.values())
VARIANTS: Tuple[str, ...] = (
    *ONE_MODEL_VARIANTS, "scalar", "scalar-init-global", "scalar-fitted", "scalar-wo-sd", "scalar-wo-ft", "scalar-s1.0", "scalar-autocap", "auto", "auto-fitted", "auto-parallel", "auto-parallel-fitted", "nerfacto",
)

#: The variants ``--budgets`` can train (the one models with either schedule, the defaults on one machine and on
#: K workers), and those it trains when ``--variants`` is left at its default.
CURVE_VARIANTS: Tuple[str, ...] = (*ONE_MODEL_VARIANTS, "auto", "auto-parallel")
DEFAULT_CURVE_VARIANTS: Tuple[str, ...] = ("ngp-t", "ngp-t2", "auto", "auto-parallel")
#: The one-model runs trained once more for the blocks' wall-clock are named ``<variant>WALL_CLOCK_SUFFIX``.
WALL_CLOCK_SUFFIX = "-wall-clock"
#: A one-model run that ends this share of the blocks' wall-clock or less before it is read at its end.
WALL_CLOCK_TOLERANCE = 0.03
#: Former variant names, still accepted (``--variants``, and run folders of earlier benchmarks read by
#: ``--resume``): former name -> name.
VARIANT_ALIASES: Dict[str, str] = {"ngp19": "ngp-t", "ngp21": "ngp-t2"}


def one_model_schedule(name: str) -> Tuple[str, str]:
    """(table size, schedule) of a one-model variant (:data:`ONE_MODEL_SCHEDULES`): ``ngp-t2-decay`` ->
    ``("ngp-t2", "decay")``. A name that is not one raises KeyError."""
    for size, schedules in ONE_MODEL_SCHEDULES.items():
        for schedule, variant in schedules.items():
            if variant == name:
                return size, schedule
    raise KeyError(f"{name!r} is not a one-model variant (one of {list(ONE_MODEL_VARIANTS)})")


def canonical_variant(name: str) -> str:
    """``name`` with a former variant name (:data:`VARIANT_ALIASES`) replaced by its new one, the names
    derived from it included (``ngp19-wall-clock-2`` -> ``ngp-t-wall-clock-2``); other names unchanged."""
    for former, new in VARIANT_ALIASES.items():
        if name == former or name.startswith(former + "-"):
            return new + name[len(former):]
    return name


def former_variant_name(name: str) -> Optional[str]:
    """The name ``name`` had before the rename (``ngp-t-wall-clock`` -> ``ngp19-wall-clock``), or None."""
    for former, new in VARIANT_ALIASES.items():
        if name == new or name.startswith(new + "-"):
            return former + name[len(new):]
    return None


@dataclass
class BenchmarkConfig:
    """Speed against error of every variant on one scene."""

    data: Optional[Path] = None
    """Scene folder (nerfstudio format). Required unless --quick (which makes a synthetic scene)."""
    downscale: int = 4
    """Image downscale factor (nerfstudio's --downscale-factor; images_4/ at 4)."""
    output_dir: Path = Path("outputs/benchmark")
    """Where results.json/.md and the plots go (runs under output_dir/runs)."""
    global_steps: int = 400
    """G: steps of the global phase."""
    block_steps: int = 100
    """B: steps of each block."""
    num_blocks: int = 4
    """K of the fixed-K variants."""
    parallel_block_steps: Optional[int] = None
    """Steps of each block in ``auto-parallel`` (equal wall-clock with K workers); default K x B, the steps
    NGP_T trains after the global phase."""
    log2_table: int = 19
    """T: log2 table size of NGP_T, of the global model and of every fixed-table block; NGP_{T+2} has 4x."""
    rays_per_batch: int = 2048
    """Training rays per step (every variant)."""
    ray_choice: Literal["uniform", "error"] = "uniform"
    """How every variant draws its training pixels (``pipeline.datamanager.pixel-sampler.ray-choice``)."""
    decoder_width: Optional[int] = None
    """Units of each hidden decoder layer in every SCALAR/NGP variant (``pipeline.model.field.hidden_dim``).
    None: the field's default. 128 is the paper's decoder."""
    eval_every: int = 200
    """Evaluate every this many steps (plus at the end of each variant)."""
    fusions: Optional[Tuple[str, ...]] = None
    """Fusion modes every block variant is evaluated with at its end, in this order (the first is the one its
    run renders with); default: each variant's own list. Each mode renders every held-out view once more."""
    match_wall_clock: bool = True
    """Train a one-model run (NGP_T, NGP_{T+2}, either schedule) that ended before the blocks' wall-clock on K
    workers once more, for that wall-clock (``<variant>-wall-clock``). Off: the table reads the shorter run's end."""
    wall_clock_tries: int = 3
    """Most runs of each one-model variant for the blocks' wall-clock: while one ends more than 3 % away from
    it, the next is planned from that run's pace; the run that ended nearest it is read."""
    heldout_view: int = 0
    """Which held-out view (index among the eval images) heldout_view.png shows, rendered by each run shown."""
    resume: bool = False
    """Reuse each variant's finished run in output_dir/runs whose spec is the one this command writes (the code
    and the scene's files are not compared): only what is missing or changed is trained."""
    seed: int = 42
    """``machine.seed`` of every variant (ns-train's default). The same seed trains the same models,
    another seed repeats the comparison from other initial weights and rays."""
    variants: Tuple[str, ...] = VARIANTS
    """Which variants to run (the block variants add the global phase they start from). ``ngp-t``: one model
    with the blocks' table 2^T; ``ngp-t2``: a 4x table; ``-decay``: one decay over the run; ngp19 / ngp21 accepted."""
    quick: bool = False
    """Synthetic 24-image scene, tiny models, a few steps: checks the harness end to end in about a minute."""
    verbose: bool = False
    """Show the variants' training output."""
    from_results: bool = False
    """Train nothing: rewrite results.md and the plots from output_dir/results.json."""
    max_auto_blocks: Optional[int] = None
    """``--pipeline.max-auto-blocks`` of every variant (None: ns-train's default): the cap of the automatic K, for
    repeating a benchmark measured under another cap (the documented ones before it was raised to 64: 8)."""
    budget_eval_shares: Tuple[float, ...] = (0.25, 0.5, 0.75)
    """With --budgets: shares of its training time at which a run is evaluated before its end (each renders every
    held-out view; none: at its end only)."""
    budgets: Optional[Tuple[str, ...]] = None
    """Speed against error to the plateau instead of equal steps: wall-clock budgets (like 5m 15m 1h 4h); every
    variant of ngp-t, ngp-t2, auto and auto-parallel in --variants trains once per budget as --pipeline.time-budget
    plans it, evaluated at 25, 50, 75 and 100 % of its time (benchmarking/curves.py). --resume continues an
    interrupted run from its checkpoint."""

    def __post_init__(self) -> None:
        # former variant names (ngp19, ngp21) become the new ones, so the run records only the new names
        self.variants = tuple(canonical_variant(v) for v in self.variants)


@dataclass
class Variant:
    name: str
    method: str
    overrides: Dict[str, Any]
    fusions: List[str] = field(default_factory=lambda: ["global"])
    base: Optional[str] = None
    """Variant whose trained global model this one starts from (its time and curve are prepended)."""
    time_limit_s: float = 0.0
    eval_every: Optional[int] = None
    """Evaluate every this many steps (None: the benchmark's --eval-every; 0: at the end only)."""


def use_quick_budgets(config: BenchmarkConfig) -> None:
    """``--quick``'s budgets (for the small synthetic scene): no downscale, a few steps, two blocks, small
    batches, tables of 2^14."""
    config.downscale, config.global_steps, config.block_steps, config.num_blocks = 1, 20, 6, 2
    config.rays_per_batch, config.eval_every, config.log2_table = 512, 10, 14


def curve_variants(config: BenchmarkConfig) -> List[str]:
    """The variants a ``--budgets`` benchmark trains, in the order asked: ``--variants`` as given (former names
    replaced by the new ones), or :data:`DEFAULT_CURVE_VARIANTS` when ``--variants`` is left at its default."""
    if tuple(config.variants) == VARIANTS:
        return list(DEFAULT_CURVE_VARIANTS)
    return list(dict.fromkeys(canonical_variant(v) for v in config.variants))


def check_options(config: BenchmarkConfig) -> None:
    """Refuse, with the option named, variants that do not exist and a parallel budget of no steps (before
    anything is written)."""
    if config.parallel_block_steps is not None and config.parallel_block_steps < 1:
        raise SystemExit(f"scalar-nerf-benchmark: --parallel-block-steps {config.parallel_block_steps}: each block needs at least 1 step")
    if config.wall_clock_tries < 1:
        raise SystemExit(f"scalar-nerf-benchmark: --wall-clock-tries {config.wall_clock_tries}: at least 1 run is needed")
    if config.heldout_view < 0:
        raise SystemExit(f"scalar-nerf-benchmark: --heldout-view {config.heldout_view}: a view index is 0 or more")
    if config.budgets is not None:
        from scalar_nerfstudio.blocks.length import LengthError, parse_duration

        if not config.budgets:
            raise SystemExit("scalar-nerf-benchmark: --budgets needs at least one budget (like 15m)")
        if not all(0.0 < share < 1.0 for share in config.budget_eval_shares):
            raise SystemExit(f"scalar-nerf-benchmark: --budget-eval-shares {config.budget_eval_shares}: each share lies between 0 and 1")
        for budget in config.budgets:
            try:
                parse_duration(budget)
            except LengthError as error:
                raise SystemExit(f"scalar-nerf-benchmark: --budgets {budget}: {error}") from None
    if config.max_auto_blocks is not None and config.max_auto_blocks < 1:
        raise SystemExit(f"scalar-nerf-benchmark: --max-auto-blocks {config.max_auto_blocks}: at least 1 block")
    if config.decoder_width is not None and config.decoder_width < 1:
        raise SystemExit(f"scalar-nerf-benchmark: --decoder-width {config.decoder_width}: a decoder layer needs at least 1 unit")
    unknown = [v for v in config.variants if canonical_variant(v) not in VARIANTS]
    if unknown:
        raise SystemExit(f"scalar-nerf-benchmark: unknown variant(s) {unknown}; choose from {list(VARIANTS)} "
                         f"(former names {list(VARIANT_ALIASES)} are accepted)")
    not_timed = [v for v in curve_variants(config) if v not in CURVE_VARIANTS] if config.budgets is not None else []
    if not_timed:
        raise SystemExit(f"scalar-nerf-benchmark: --variants {' '.join(not_timed)}: not trained by --budgets; "
                         f"choose from {list(CURVE_VARIANTS)}")
    if config.fusions is not None:
        from scalar_nerfstudio.fusion import FusionModeError, parse_fusion_mode

        if not config.fusions:
            raise SystemExit("scalar-nerf-benchmark: --fusions needs at least one fusion mode")
        for mode in config.fusions:
            try:
                parse_fusion_mode(mode)
            except FusionModeError as error:
                raise SystemExit(f"scalar-nerf-benchmark: --fusions {mode}: {error}") from None


def parallel_block_steps(config: BenchmarkConfig) -> int:
    """Steps of each block in the ``auto-parallel`` variants: ``--parallel-block-steps``, else K x B (the
    steps NGP_T trains after the global phase)."""
    return config.parallel_block_steps if config.parallel_block_steps is not None else config.num_blocks * config.block_steps


def _tables(config: BenchmarkConfig) -> Tuple[int, int, Dict[str, Any]]:
    """(log2 T of NGP_T, of NGP_{T+2}, field/sampling overrides shared by all our variants)."""
    shared: Dict[str, Any] = {}
    if config.quick:
        shared.update({
            "pipeline.model.field.max_resolution": 256, "pipeline.model.num_samples_per_ray": 32,
            "pipeline.model.occupancy_warmup_steps": 8,
        })
    if config.decoder_width is not None:
        shared["pipeline.model.field.hidden_dim"] = config.decoder_width
    if config.max_auto_blocks is not None:
        shared["pipeline.max_auto_blocks"] = config.max_auto_blocks
    shared.update(ray_choice_overrides(config))
    return config.log2_table, config.log2_table + 2, shared


def ray_choice_overrides(config: BenchmarkConfig) -> Dict[str, Any]:
    """The pixel sampler's override for ``--ray-choice`` (none for nerfstudio's uniform draw, so the specs of
    runs measured before the option existed still match under ``--resume``)."""
    if config.ray_choice == "uniform":
        return {}
    return {"pipeline.datamanager.pixel_sampler.ray_choice": config.ray_choice}


def auto_k(config: BenchmarkConfig, log2_t: int) -> int:
    """The automatic K scalar-nerf would choose on this scene (same rule as the pipeline)."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from scalar_nerfstudio.data.datamanager import parsed_layout_scale
    from scalar_nerfstudio.pipeline import ScalarPipelineConfig

    if config.data is None:  # set by the schedule (--data, or --quick's own scene) before any K is chosen
        raise SystemExit("scalar-nerf-benchmark: no --data scene to choose the automatic K on")
    parsed = NerfstudioDataParserConfig(
        data=config.data, downscale_factor=config.downscale, eval_mode="interval", eval_interval=8
    ).setup().get_dataparser_outputs("train")
    pipeline = ScalarPipelineConfig()
    pipeline.model.field.log2_hashmap_size = log2_t
    if config.max_auto_blocks is not None:
        pipeline.max_auto_blocks = config.max_auto_blocks
    return pipeline.automatic_num_blocks(parsed_layout_scale(parsed), len(parsed.image_filenames))


def plan(config: BenchmarkConfig) -> Tuple[List[Variant], Dict[str, str]]:
    """The variants to run, in order, and notes (e.g. a variant that is the same as another)."""
    g, b, k = config.global_steps, config.block_steps, config.num_blocks
    total = g + k * b
    log2_t, log2_t2, shared = _tables(config)
    common = {**shared, "pipeline.datamanager.train_num_rays_per_batch": config.rays_per_batch, "pipeline.model.field.log2_hashmap_size": log2_t}
    fixed_tables = {"pipeline.block_log2_hashmap_size": log2_t, "pipeline.block_max_resolution": 256 if config.quick else 2048}
    single = {**common, "pipeline.num_blocks": 1, "pipeline.train_blocks": False, "pipeline.global_steps": total}
    blocks = {**common, "pipeline.num_blocks": k, "pipeline.global_steps": 0, "pipeline.block_steps": b}
    paper = {**blocks, **fixed_tables, "pipeline.block_init": "fresh"}  # the paper's blocks: empty tables of their own
    notes: Dict[str, str] = {}
    check_options(config)
    wanted = [canonical_variant(v) for v in config.variants]
    out: List[Variant] = []
    if any(v.startswith(("scalar", "auto")) or v == "nerfacto" for v in wanted):
        out.append(Variant("global", "scalar-nerf", {**common, "pipeline.num_blocks": k, "pipeline.train_blocks": False, "pipeline.global_steps": g}))
    for name in wanted:
        if name in ONE_MODEL_VARIANTS:
            size, schedule = one_model_schedule(name)
            table = {"pipeline.model.field.log2_hashmap_size": log2_t2} if size == "ngp-t2" else {}
            decay = {"pipeline.one_model_restart": 0.0} if schedule == "decay" else {}
            out.append(Variant(name, "scalar-nerf", {**single, **table, **decay}))
        elif name == "scalar":
            out.append(Variant(name, "scalar-nerf", paper,
                               ["global", "surface", "idw", "nearest", "global-only"], base="global"))
        elif name == "scalar-init-global":
            out.append(Variant(name, "scalar-nerf", {**blocks, **fixed_tables, "pipeline.block_init": "global"},
                               ["nearest", "global", "surface", "idw", "global-only"], base="global"))
        elif name == "scalar-fitted":
            out.append(Variant(name, "scalar-nerf", {**blocks, **fixed_tables, "pipeline.block_init": "fitted"},
                               ["nearest", "global", "surface", "global-only"], base="global"))
        elif name == "scalar-wo-sd":
            out.append(Variant(name, "scalar-nerf", {**paper, "pipeline.decoder_mode": "independent"}, ["global", "idw"], base="global"))
        elif name == "scalar-wo-ft":
            out.append(Variant(name, "scalar-nerf", {**paper, "pipeline.decoder_mode": "frozen"}, base="global"))
        elif name == "scalar-s1.0":
            out.append(Variant(name, "scalar-nerf", {**paper, "pipeline.aabb_scale": [1.0, 1.0, 1.0]}, base="global"))
        elif name == "scalar-autocap":
            out.append(Variant(name, "scalar-nerf", {**blocks, "pipeline.block_init": "fresh"}, base="global"))
        elif name in ("auto", "auto-fitted", "auto-parallel", "auto-parallel-fitted"):
            from scalar_nerfstudio.models.scene_model import ScalarSceneModelConfig

            default_fusion = ScalarSceneModelConfig.fusion
            chosen = auto_k(config, log2_t)
            if chosen == 1:
                notes[name] = f"automatic K = 1 on this scene: one 2^{log2_t} model of {total} steps, the same configuration as ngp-t"
                if "ngp-t" not in wanted and not any(v.name == "ngp-t" for v in out):
                    out.append(Variant("ngp-t", "scalar-nerf", single))
            else:
                parallel = name.startswith("auto-parallel")
                steps = parallel_block_steps(config) if parallel else k * b // chosen
                notes[name] = (f"automatic K = {chosen}, {steps} steps per block ({chosen * steps} block steps in all), "
                               f"automatic block tables: the equal wall-clock budget with {chosen} workers") if parallel else (
                    f"automatic K = {chosen}, {steps} steps per block, automatic block tables")
                automatic = {**blocks, "pipeline.num_blocks": None, "pipeline.block_steps": steps}
                if name.endswith("fitted"):
                    automatic["pipeline.block_init"] = "fitted"
                # the same blocks: nearest without the guard, and the two nearest blended
                blended = [mode for mode in ("nearest", "nearest-guarded", "nearest-idw") if mode != default_fusion]
                fusions = ([default_fusion, *blended, "global", "global-only"] if name == "auto"
                           else [default_fusion, *blended, "global-only"])
                out.append(Variant(name, "scalar-nerf", automatic, fusions, base="global", eval_every=0 if parallel else None))
        elif name == "nerfacto":
            overrides: Dict[str, Any] = {"pipeline.datamanager.train_num_rays_per_batch": config.rays_per_batch}
            if config.quick:
                overrides.update({"pipeline.datamanager.train_num_rays_per_batch": 256, "pipeline.model.eval_num_rays_per_chunk": 4096})
            out.append(Variant(name, "nerfacto", overrides))
    if config.fusions is not None:
        for variant in out:
            if variant.base is not None:  # the block variants; one-model runs render one model
                variant.fusions = list(config.fusions)
    return out, notes


def blocks_wall_clock_s(results: Dict[str, Dict[str, Any]]) -> float:
    """The blocks' wall-clock on K workers: the longest ``parallel_train_s`` in ``results`` (a block
    variant's global phase plus its slowest block, :func:`.schedule.with_base_phase`); 0 without one."""
    return max((float(r["parallel_train_s"]) for r in results.values() if r.get("parallel_train_s")), default=0.0)


def _pace(run: Dict[str, Any]) -> float:
    """A run's steps per second of training."""
    return run["steps"] / max(float(run["train_s"]), 1e-9)


def _planned_for(variant: Variant, name: str, run: Dict[str, Any], seconds: float) -> Variant:
    """A copy of the one-model ``variant`` named ``name`` that trains the steps ``run``'s pace fits in
    ``seconds``, from the start, evaluated at its end only."""
    steps = min(math.ceil(seconds * _pace(run)), 10 * int(run["steps"]))  # (a run timed at ~0 s plans 10x its steps, not 10^13)
    return Variant(name, variant.method, {**variant.overrides, "pipeline.global_steps": steps}, list(variant.fusions), eval_every=0)


def wall_clock_variants(
    config: BenchmarkConfig, variants: List[Variant], results: Dict[str, Dict[str, Any]]
) -> List[Tuple[Variant, str]]:
    """The one-model runs to train once more, with a note each, so that the equal wall-clock comparison
    reads a run as long as the blocks' (``--match-wall-clock``).

    The blocks' wall-clock is :func:`blocks_wall_clock_s`. A one-model variant of ``variants``
    (:data:`ONE_MODEL_VARIANTS`: ``ngp-t``, ``ngp-t2`` and their ``-decay`` runs) whose run in
    ``results`` ended more than :data:`WALL_CLOCK_TOLERANCE` of it
    earlier gets a copy named ``<name>-wall-clock`` that trains ``ceil(wall-clock x steps / train_s)``
    steps, its first run's pace, from the start: its learning-rate schedule then spans the longer run. It is
    evaluated at its end only. When it too ends away from the wall-clock, :func:`wall_clock_retry` plans
    the next run."""
    seconds = blocks_wall_clock_s(results)
    if not config.match_wall_clock or seconds <= 0.0:
        return []
    out: List[Tuple[Variant, str]] = []
    for variant in variants:
        first = results.get(variant.name)
        if variant.name not in ONE_MODEL_VARIANTS or first is None or first["train_s"] >= seconds * (1.0 - WALL_CLOCK_TOLERANCE):
            continue
        again = _planned_for(variant, variant.name + WALL_CLOCK_SUFFIX, first, seconds)
        note = (f"{variant.name} trained again from the start, first for {again.overrides['pipeline.global_steps']} steps: its first run of "
                f"{first['steps']} steps ended at {first['train_s']:.0f} s, the blocks on K workers at {seconds:.0f} s ({_pace(first):.1f} steps/s)")
        out.append((again, note))
    return out


def wall_clock_retry(config: BenchmarkConfig, tried: List[Tuple[Variant, Dict[str, Any]]], seconds: float) -> Optional[Variant]:
    """The next run of a one-model variant trained for the blocks' wall-clock ``seconds``, or None.

    ``tried``: its runs so far (the first is ``<name>-wall-clock`` of :func:`wall_clock_variants`) with
    their results. None when the last ended within :data:`WALL_CLOCK_TOLERANCE` of ``seconds``, when
    ``config.wall_clock_tries`` runs were trained, or when the last run's pace plans a step count already
    tried. Else ``<name>-wall-clock-<n>``: the steps the last run's own pace fits in ``seconds``."""
    variant, last = tried[-1]
    if abs(float(last["train_s"]) - seconds) <= WALL_CLOCK_TOLERANCE * seconds or len(tried) >= config.wall_clock_tries:
        return None
    name = tried[0][0].name + f"-{len(tried) + 1}"
    again = _planned_for(variant, name, last, seconds)
    if again.overrides["pipeline.global_steps"] in {v.overrides["pipeline.global_steps"] for v, _ in tried}:
        return None
    return again


def nearest_to_wall_clock(tried: List[Tuple[Variant, Dict[str, Any]]], seconds: float) -> Tuple[Dict[str, Any], str]:
    """Of a one-model variant's runs for the blocks' wall-clock ``seconds`` (with their results), the
    result of the one that ended nearest it (of two as near, the one that trained more steps: the
    comparison then errs towards the one model), with a note of every run's steps, time and PSNR."""
    variant, chosen = min(tried, key=lambda pair: (round(abs(float(pair[1]["train_s"]) - seconds), 1), -int(pair[1]["steps"])))
    runs = "; ".join(f"{v.name}: {r['steps']} steps in {r['train_s']:.0f} s, {r['final'].get('psnr', float('nan')):.2f} dB"
                     for v, r in tried)
    return chosen, f"{len(tried)} run(s) for the blocks' {seconds:.0f} s ({runs}); read: {variant.name}"
