"""Training recipes: one typed object holds everything a training chain is trained with.

A :class:`Recipe` names the model preset (the network sizes and resolutions
live in :mod:`genre_backend.config`; the recipe names one, it does not copy
them) and gives one :class:`StageRecipe` per stage: learning rate, Adam
betas, batch size, loss weights and step budget.  ``genre train STAGE
--recipe NAME`` starts from a named recipe; any explicit option overrides
its value.  The named recipes:

* ``paper``: the paper's optimiser numbers (lr 1e-3 for the depth net and the
  one-step baseline, 1e-4 for the inpainting net, refiner and 3D Completion,
  1e-5 for the joint stage; surface weight 10); ``genre train``'s default.
* ``shipped``: what made the shipped default weights (``genre chain protocol``, :mod:`training.chain`):
  the voxel stages with surface weight 0.1 and (refiner, 3D Completion) lr
  1e-3, and the step budgets of the 2-core CPU chain.  Why they depart from
  the paper: ARCHITECTURE.md.
* ``sharp``: ``shipped`` with the voxel stages on the truncated-distance
  target (``GeometryConfig.target = "distance"``), continued from the shipped
  weights.
* ``product``: the weights users get (``genre chain product``), on
  every class of the corpus and the procedural shapes: every stage continues
  from the shipped weights on photo-composited renders; after the first
  chain, training accumulates in the joint stage, which then trains all three
  nets end to end with the depth net's own loss added (``depth_weight``).
* ``product_full``: ``product`` with the refiner grown by a non-linear
  full-resolution branch (``NetworkConfig.refiner_full_nf``), trained in a
  refine stage from the installed default weights before the joint rounds.
* ``cycle``: one cycle of the product weights from the installed file (``genre chain product-cycle``): the
  depth, refine and joint stages in the installed file's own regime (lr 3e-5, every picture on the grey
  backdrop), the settings of the runs behind the installed weights since 2026-12-05 (``results/decisions.md``).
* ``photo``: ``shipped`` with the depth stage continued (``--init`` the
  shipped weights) on renders composited over real photographs, so that the
  silhouette and depth work on photos.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

__all__ = ["STAGES", "documented", "StageRecipe", "Recipe", "RECIPES", "get_recipe", "BurstRecipe", "BURST_RECIPES", "get_burst_recipe"]

STAGES = ("depth", "inpaint", "refine", "joint", "completion", "onestep")


def documented(default, text: str):
    """A field with its default and the one line ``genre train --help`` prints for it."""
    return field(default=default, metadata={"help": text})


@dataclass(frozen=True)
class StageRecipe:
    """How one stage trains: Adam(lr, betas) on batches of ``batch_size`` for ``steps`` steps.

    Each field's ``help`` (its metadata) says what it does; ``genre train --help`` prints it.  Photo compositing:
    :mod:`training.data.dataset`; ``mirror`` is an exact augmentation (:func:`training.data.dataset.mirror_sample`);
    ``stretch`` (:func:`training.data.dataset.stretch_sample`) too; ``sph_teacher``, ``depth_dropout``, ``mirror`` and
    ``stretch`` touch neither validation nor inference; ``backdrop``'s share does not either, but a model whose
    ``geometry.plain_backdrop`` is on is validated on painted pictures, as it is shown them in use.
    """

    lr: float = field(metadata={"help": "Adam's learning rate"})
    steps: int = documented(1000, "the stage's step budget (a resumed run counts its steps so far)")
    batch_size: int = documented(4, "samples a step, per process")
    beta1: float = documented(0.5, "Adam's beta1")
    beta2: float = documented(0.9, "Adam's beta2")
    weight_decay: float = documented(0.0, "decoupled weight decay (AdamW) of the convolutions' and linear maps' weights: "
                                          "each shrinks by lr times this a step (0: Adam, no decay)")
    surface_weight: float = documented(10.0, "voxel stages: the weight of the BCE over the true shell's voxels, added to the "
                                             "BCE over the whole grid")
    photo_fraction: float = documented(0.0, "the share of samples composited over real photographs, with a camera's faults "
                                            "(needs --backgrounds)")
    sph_loss: str = documented("mse", "the spherical maps' loss (inpaint, joint, onestep): 'mse' (the paper's) or 'l1'")
    depth_weight: float = documented(0.0, "joint: the depth net's own loss (depth and silhouette) added with this weight")
    depth_gradient_weight: float = documented(0.0, "depth, joint: this weight times the multi-scale gradient matching term "
                                                   "added to the depth's MSE (0: the MSE alone)")
    depth_offset_weight: float = documented(1.0, "depth, joint: the depth's MSE splits exactly into each view's offset "
                                                 "(its error's mean over the mask) and its relief (the rest); the offset "
                                                 "counts this many times (1: the plain MSE; below 1 the relief weighs more)")
    normals_weight: float = documented(0.0, "depth: this weight times the loss (1 - cos) of a training-only normals head "
                                            "on the depth net's encoder (training.learn.normals; 0: no head)")
    outline_weight: float = documented(0.0, "refine, joint: this weight times the BCE between the predicted and the true "
                                            "grid's silhouettes through the view's camera (0: off)")
    lr_halflife: int = documented(0, "the learning rate halves every this many steps, counted from the stage's first step "
                                     "(0: a constant rate)")
    sph_teacher: float = documented(0.0, "refine: the share of training samples fed the true full map instead of the "
                                         "inpainted one")
    depth_dropout: float = documented(0.0, "refine, joint: the share of training samples whose depth voxels are emptied, so "
                                           "that the refiner builds them from the spherical map alone")
    mirror: float = documented(0.0, "the share of training samples reflected left to right, targets with them")
    stretch: float = documented(0.0, "depth: the share of training samples whose object is stretched across (a new "
                                     "object's exact view: picture, depth and mask scaled left to right about the "
                                     "image centre by a factor log-uniform in [0.7, 1.4], kept inside the frame)")
    backdrop: float = documented(0.0, "the share of training samples painted the neutral grey outside their mask, as the "
                                      "mesh option plain_backdrop paints a photo (after the camera's faults)")
    hull_grad_width: float = documented(1.0, "refine, joint, for weights that store sph_hull_carve: the trim's gradient "
                                             "reaches voxels within half this many voxels of the map's hull (a ramp this "
                                             "wide, straight through; the forward pass stays the mesh option's)")
    depth_lr_scale: float = documented(1.0, "joint: the depth net's learning rate as a multiple of lr (0: the depth net "
                                            "stays as the starting weights give it, batch-norm statistics too, and only the inpainting "
                                            "net and the refiner train, end to end on its depth)")

    def __post_init__(self):
        if isinstance(self.lr, bool) or not isinstance(self.lr, (int, float)) or not (math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr: expected a positive finite number, got {self.lr!r}")
        for name in ("steps", "batch_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected a positive int, got {value!r}")
        for name in ("beta1", "beta2"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"{name}: expected a number in [0, 1), got {getattr(self, name)!r}")
        if not (math.isfinite(self.surface_weight) and self.surface_weight >= 0):
            raise ValueError(f"surface_weight: expected a finite number >= 0, got {self.surface_weight!r}")
        for name in ("photo_fraction", "sph_teacher", "depth_dropout", "mirror", "stretch", "backdrop"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise ValueError(f"{name}: expected a number in [0, 1], got {value!r}")
        if isinstance(self.lr_halflife, bool) or not isinstance(self.lr_halflife, int) or self.lr_halflife < 0:
            raise ValueError(f"lr_halflife: expected an int >= 0 (0: a constant rate), got {self.lr_halflife!r}")
        for name in ("depth_weight", "depth_gradient_weight", "depth_offset_weight", "normals_weight", "outline_weight", "depth_lr_scale",
                     "weight_decay"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {value!r}")
        if isinstance(self.hull_grad_width, bool) or not isinstance(self.hull_grad_width, (int, float)) or not (
                math.isfinite(self.hull_grad_width) and self.hull_grad_width >= 1.0):
            raise ValueError(f"hull_grad_width: expected a finite number of voxels >= 1, got {self.hull_grad_width!r}")
        if self.sph_loss not in ("mse", "l1"):
            raise ValueError(f"sph_loss: expected 'mse' or 'l1', got {self.sph_loss!r}")

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


@dataclass(frozen=True)
class Recipe:
    """A named training recipe: the model preset and one :class:`StageRecipe` per stage."""

    name: str
    preset: str
    stages: dict[str, StageRecipe] = field(default_factory=dict)
    description: str = ""
    # the voxel representation the voxel stages learn (GeometryConfig.target); None: the model's own
    # (the preset's, or what --init weights were trained on)
    target: str | None = None
    # the width of the refiner's full-resolution branch (NetworkConfig.refiner_full_nf); None: the model's
    # own.  A model without one that starts a stage of this recipe is grown (genre_backend.nets.model.grow_refiner).
    refiner_full_nf: int | None = None

    def __post_init__(self):
        missing = [s for s in STAGES if s not in self.stages]
        unknown = [s for s in self.stages if s not in STAGES]
        if missing or unknown:
            raise ValueError(f"recipe {self.name!r}: stages missing {missing}, unknown {unknown}")

    def stage(self, name: str) -> StageRecipe:
        if name not in self.stages:
            raise ValueError(f"recipe {self.name!r}: no stage {name!r}; stages: {', '.join(STAGES)}")
        return self.stages[name]


_PAPER = Recipe(
    name="paper",
    preset="default",
    description="the paper's optimiser numbers (genre train's defaults)",
    stages={
        "depth": StageRecipe(lr=1e-3),
        "inpaint": StageRecipe(lr=1e-4),
        "refine": StageRecipe(lr=1e-4),
        "joint": StageRecipe(lr=1e-5),
        "completion": StageRecipe(lr=1e-4),
        "onestep": StageRecipe(lr=1e-3),
    },
)

_VOXEL = {"surface_weight": 0.1}  # (the voxel stages: refine, joint, completion)
_SHIPPED = Recipe(
    name="shipped",
    preset="default",
    description="the shipped default weights' chain on a 2-core CPU (genre chain protocol)",
    stages={
        "depth": replace(_PAPER.stages["depth"], steps=6000),
        "inpaint": replace(_PAPER.stages["inpaint"], steps=3000),
        "refine": replace(_PAPER.stages["refine"], steps=3000, lr=1e-3, **_VOXEL),
        "joint": replace(_PAPER.stages["joint"], steps=400, **_VOXEL),
        # the baselines get the same budgets: 3D Completion the refiner's, 1-step half the depth net's
        "completion": replace(_PAPER.stages["completion"], steps=3000, lr=1e-3, **_VOXEL),
        "onestep": replace(_PAPER.stages["onestep"], steps=3000),
    },
)

_PHOTO = Recipe(
    name="photo",
    preset="default",
    description="photo-like depth net: the shipped chain with the depth stage continued from the shipped "
                "weights on renders composited over real photographs (genre data backgrounds), 80 % of samples",
    stages={**_SHIPPED.stages, "depth": replace(_SHIPPED.stages["depth"], steps=3000, lr=5e-4, photo_fraction=0.8)},
)

_SHARP = Recipe(
    name="sharp",
    preset="default",
    target="distance",
    description="the shipped chain moved to the truncated-distance target: every stage continues from the shipped "
                "weights (--init; the depth net is kept) with the shipped budgets: the inpainting net 3,000 more "
                "steps, the refiner and the 3D Completion net (which starts from the same refiner) 3,000 steps each "
                "on the distance target, joint 400; the 1-step baseline afresh, 3,000",
    stages={**_SHIPPED.stages},
)

_PRODUCT = Recipe(
    name="product",
    preset="default",
    target="distance",
    description="the product model on every class and the procedural shapes (genre chain product): the depth net "
                "2,000 steps on photo-composited renders (80 %), the inpainting net 2,000, the refiner 3,000, all from "
                "the shipped weights; then the joint stage trains every net end to end (lr 1e-4, the depth loss added, "
                "photo compositing on; the rate halves every 1,200 steps), its budget raised round after round",
    stages={
        **_SHIPPED.stages,
        "depth": replace(_PHOTO.stages["depth"], steps=2000),
        "inpaint": replace(_SHIPPED.stages["inpaint"], steps=2000),
        "refine": replace(_SHIPPED.stages["refine"], steps=3000),
        "joint": replace(_SHIPPED.stages["joint"], steps=600, lr=1e-4, photo_fraction=0.8, depth_weight=1.0, lr_halflife=1200),
    },
)

_PRODUCT_FULL = Recipe(
    name="product_full",
    preset="default",
    target="distance",
    refiner_full_nf=8,
    description="the product model with a full-resolution refiner branch (8 channels): the refine stage grows it on the "
                "installed default weights and trains the refiner (the other nets frozen) 2,400 steps, lr 1e-3 halving "
                "every 800; then the product's joint rounds",
    stages={**_PRODUCT.stages, "refine": replace(_PRODUCT.stages["refine"], steps=2400, lr_halflife=800)},
)

# the settings every stage has trained the installed product weights with since the grey-backdrop joint stage
# (C73b; results/decisions.md 2026-12-04 and 2026-12-05): a low rate, batch 8 a process, every picture on the grey
# backdrop, as the installed file paints photos (geometry.plain_backdrop)
_CYCLE_COMMON = dict(lr=3e-5, lr_halflife=3000, batch_size=8, photo_fraction=0.8, backdrop=1.0)
_CYCLE = Recipe(
    name="cycle",
    preset="default",
    target="distance",
    description="one cycle of the product weights from the installed file (genre chain product-cycle): the depth "
                "stage 3,000 steps (the depth's gradient term at 2, half the pictures mirrored, weight decay 0.5), "
                "the refine stage 2,400 steps on that depth, then the joint stage 8,000 steps; every stage at lr 3e-5 "
                "halving every 3,000 steps, batch 8 a process, 80 % of the pictures over photos and every picture on "
                "the grey backdrop",
    stages={
        **_PRODUCT.stages,
        "depth": replace(_PRODUCT.stages["depth"], **_CYCLE_COMMON, steps=3000, depth_gradient_weight=2.0, mirror=0.5,
                         weight_decay=0.5),
        "refine": replace(_PRODUCT.stages["refine"], **_CYCLE_COMMON, steps=2400),
        "joint": replace(_PRODUCT.stages["joint"], **_CYCLE_COMMON, steps=8000, depth_gradient_weight=2.0, mirror=0.5),
    },
)

RECIPES: dict[str, Recipe] = {r.name: r for r in (_PAPER, _SHIPPED, _PHOTO, _SHARP, _PRODUCT, _PRODUCT_FULL, _CYCLE)}


def get_recipe(name: str) -> Recipe:
    try:
        return RECIPES[name]
    except KeyError:
        raise ValueError(f"unknown recipe {name!r}; choose one of {sorted(RECIPES)}") from None


@dataclass(frozen=True)
class BurstRecipe:
    """How a GPU burst trains (:mod:`training.learn.burst`): the inpainting net and the refiner together,
    from true depth maps of the pack's meshes seen from random views, for a wall-clock budget.

    ``preset``: the model preset whose nets (NetworkConfig) the burst trains
    (:mod:`genre_backend.config`; None: the ``--init`` weights' own); the
    geometry stays the ``--init`` weights'.  Every tensor whose name and shape
    match is copied from ``--init``; the others start afresh.  ``lr`` peaks after
    ``warmup_s`` seconds and follows a cosine to ``lr_final`` × lr at the end
    of the budget.  Views: azimuth uniform, elevation uniform in
    [``elevation_min_deg``, ``elevation_max_deg``].  ``depth_noise``: the
    standard deviation (scene units) of a smooth random field added to the
    true depth before the partial map is made (the depth net's errors are
    smooth and ~1 voxel; 0 = the true depth).  ``grid_factor``: the object-frame
    distance grid of each shape is this many times finer than the voxel grid
    (the view's target is resampled from it).
    """

    name: str
    description: str
    preset: str | None = None
    lr: float = 1e-3
    lr_final: float = 0.05
    warmup_s: float = 20.0
    beta1: float = 0.9
    beta2: float = 0.999
    weight_decay: float = 0.0
    batch_size: int = 64
    surface_weight: float = 0.1
    sph_loss: str = "mse"
    sph_weight: float = 1.0
    elevation_min_deg: float = -10.0
    elevation_max_deg: float = 88.0
    depth_noise: float = 0.01
    grid_factor: int = 2
    total_steps: int = 0  # > 0: the schedule follows steps (genre train session), not the wall clock
    warmup_steps: int = 0
    sph_teacher: float = 0.0  # the share of samples whose refiner input is the true full map (genre train session)
    reuse: int = 1  # genre train session: each made sample is trained on this many times on average (a replay buffer)
    buffer_steps: int = 0  # ... drawn from the samples of the last this many steps (0: the current step's only)
    # genre train session --views: the share of fresh samples whose depth is the depth net's prediction on a render
    # (training.learn.view_bank) instead of the true depth plus noise
    bank_share: float = 0.0

    def __post_init__(self):
        for name in ("lr", "lr_final", "beta1", "beta2", "surface_weight", "sph_weight", "depth_noise", "warmup_s",
                     "weight_decay", "sph_teacher", "bank_share"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {value!r}")
        if not (self.lr > 0 and self.lr_final <= 1 and self.beta1 < 1 and self.beta2 < 1):
            raise ValueError("lr must be > 0, lr_final ≤ 1, betas < 1")
        for name in ("sph_teacher", "bank_share"):
            if getattr(self, name) > 1:
                raise ValueError(f"{name}: a share in [0, 1], got {getattr(self, name)!r}")
        for name in ("batch_size", "grid_factor", "reuse"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected a positive int, got {value!r}")
        for name in ("total_steps", "warmup_steps", "buffer_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name}: expected an int >= 0, got {value!r}")
        if not -90.0 < self.elevation_min_deg <= self.elevation_max_deg < 90.0:
            raise ValueError(f"elevation range [{self.elevation_min_deg}, {self.elevation_max_deg}] must lie in (-90, 90)")
        if self.sph_loss not in ("mse", "l1"):
            raise ValueError(f"sph_loss: expected 'mse' or 'l1', got {self.sph_loss!r}")


BURST_RECIPES: dict[str, BurstRecipe] = {r.name: r for r in (
    BurstRecipe(
        name="keep",
        description="the --init weights' widths, every tensor warm-started: the same nets trained longer",
    ),
    BurstRecipe(
        name="wide",
        description="the preset 'wide': the refiner twice as wide at the fine levels (base 16, capped at 64) with a "
                    "16-channel full-resolution branch, 2.4 M parameters as today's, starting afresh; the inpainting "
                    "net kept from --init",
        preset="wide",
    ),
    BurstRecipe(
        name="session",
        description="genre train session on the CPU: the --init weights' own nets warm-started, batch 16, lr 5e-4 "
                    "with a 200-step warm-up and a cosine to 5 % over 40,000 steps (several sessions), then flat; "
                    "4 fresh views a step, the batch drawn from the last 250 steps' views (each seen ~4 times)",
        lr=5e-4, batch_size=16, total_steps=40_000, warmup_steps=200, reuse=4, buffer_steps=250,
    ),
    BurstRecipe(
        name="session-both",
        description="genre train session --nets both on the CPU: the inpainting net and the refiner together, batch 4, "
                    "lr 5e-4 with a 200-step warm-up and a cosine to 5 % over 20,000 steps; a quarter of the samples "
                    "feed the refiner the true full map (so that it learns to use the map); 2 fresh views a step, the "
                    "batch drawn from the last 100 steps' views",
        lr=5e-4, batch_size=4, total_steps=20_000, warmup_steps=200, reuse=2, buffer_steps=100, sph_teacher=0.25,
    ),
    BurstRecipe(
        name="session-bank",
        description="session-both with rendered views (genre train session --views): three quarters of the fresh "
                    "samples take their depth from the depth net's prediction on a render, the rest the true depth "
                    "plus noise; a tenth feed the refiner the true full map",
        lr=5e-4, batch_size=4, total_steps=20_000, warmup_steps=200, reuse=2, buffer_steps=100, sph_teacher=0.1,
        bank_share=0.75,
    ),
    BurstRecipe(
        name="session-bank-ft",
        description="session-bank as a fine-tune of the installed nets (--init default): lr 1.5e-4 with a 100-step "
                    "warm-up and a cosine to 5 % over 8,000 steps (one session), so that the refiner the product "
                    "ships keeps what it knows while it learns the installed depth net's errors from every angle",
        lr=1.5e-4, batch_size=4, total_steps=8_000, warmup_steps=100, reuse=2, buffer_steps=100, sph_teacher=0.1,
        bank_share=0.75,
    ),
    BurstRecipe(
        name="fit-oracle",
        description="a diagnosis, not a product recipe (scripts/fit_oracle.sh): can the refiner fit a few shapes "
                    "when every input is true? genre train session --nets both on a small pack, the refiner always "
                    "fed the true depth (no added error) and the true full map; lr 5e-4, 100-step warm-up, cosine "
                    "to 5 % over 3,000 steps of batch 4 (2 fresh views a step, the batch from the last 50 steps')",
        lr=5e-4, batch_size=4, total_steps=3_000, warmup_steps=100, reuse=2, buffer_steps=50, sph_teacher=1.0,
        depth_noise=0.0,
    ),
)}


def get_burst_recipe(name: str) -> BurstRecipe:
    try:
        return BURST_RECIPES[name]
    except KeyError:
        raise ValueError(f"unknown burst recipe {name!r}; choose one of {sorted(BURST_RECIPES)}") from None
