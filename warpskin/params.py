"""The parameter classes of the scene sections a run reads (``[solver]``, ``[collision]``,
``[popping]``), declared with their settings (:mod:`warpskin.settings`) in a module that imports no
Warp kernels, so that the command-line parser, which makes its options from these declarations,
starts without compiling or loading any. :mod:`warpskin.solver`, :mod:`warpskin.collision` and
:mod:`warpskin.popping` export them where they are used.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from .errors import SceneError
from .settings import check_settings, setting

if TYPE_CHECKING:
    from .popping.activation import ActivationTimeline

__all__ = ["SolverParams", "RunLimits", "CollisionParams", "PoppingSettings"]


def _no_activation():
    """An empty activation timeline (no muscle group pops)."""
    from .popping.activation import ActivationTimeline

    return ActivationTimeline()


@dataclass(frozen=True)
class SolverParams:
    """Solver settings (Table 1 of the paper: 20 elasticity iterations for the Arm): what the
    solver reads, and ``dt``, the largest substep a run splits its frames into. The limits a run
    stops at are :class:`RunLimits` (the same ``[solver]`` section). Frozen: a changed copy is
    ``dataclasses.replace(params, ...)``.

    Attributes:
        iterations: Elasticity-loop iterations per step (``N_elasticity``), >= 1.
        volume_iterations: Volume-loop iterations per step (``N_volume``; the paper uses 4), >= 0.
        rotation_iterations: Warm-started rotation-extraction iterations per region fit, >= 1.
        dt: Largest substep [s] (the paper uses 5 ms); frames are split into equal substeps,
            none longer than gravity allows for the skin's edges
            (:func:`~warpskin.solver.gravity_step_limit`: ``simulate`` splits further, with one
            warning, where ``dt`` is longer).
        gravity: External acceleration [m/s^2] (default: 9.81 down the Y axis), applied in the
            file's length unit as ``units`` takes it.
        units: ``"auto"``: physics takes the file's length unit as the power of ten of the metre
            that brings the character nearest human size (:func:`warpskin.units.metres_per_unit`:
            a character 155 units across in centimetres, one 0.0012 across in kilometres, one
            0.54-5.4 across in metres), so that a character gives the same result relative to its
            size at any power-of-ten scale of its file; ``"file"``: the file is in metres.
        damping: Velocity damping rate [1/s]: ``v *= exp(-damping dt)`` per step, >= 0.
        fast_summation: Region sums by prefix scans along paths (True) or direct gather (False).
        volume_stiffness: Stiffness of the volume constraints in [0, 1].
        volume_along_normals: The volume constraints move the skin along its surface normals
            (a third of each vertex's triangles' area-weighted normals, the surface part of
            the volume gradient), weighted by inverse masses floored at the skin's median mass,
            in place of the paper's full gradient and inverse masses: a cut loop's vertices do
            not slide along the bone by the closing fans' part of the gradient, and thin tissue
            (light particles near their bone) does not take most of a sub-volume's correction.
            ``warpskin pop`` turns it on (a pop's volume is taken back near the muscle, not at
            a neck's thin tissue), its normal-only guide too.
        tether: Every particle stays within ``tether x its vertex's tissue depth + tether_floor
            x the body's diagonal`` of its LBS target (a maximum-distance constraint, applied
            once per step after the elasticity loop; the volume loop may then move a particle
            past it by its sub-volume's correction), so that no part swings far from the
            animation and thin tissue (head, hands, feet) wobbles less than the bulk; 0 turns
            it off. Tissue depth: the distance from the skin vertex to its bone layer at rest.
            Each volume iteration is followed by the cap (``tether_max``), a hard bound (without
            volume constraints, the cap follows the self-collision fail-safe).
        tether_floor: See ``tether``; a fraction of the rest bounding-box diagonal.
        tether_max: No tether radius exceeds this fraction of the diagonal, so that a run the
            tether holds is not stopped by the ``max_offset`` check (deep tissue of a
            low-poly body would otherwise get a radius above it); no particle is farther than
            this from its LBS target at the end of a step. A flex as deep as the procedural
            arm's 150 degrees, whose crease skin lies far from its collapsed LBS, needs more
            than the default (the arm scene sets its own).
        tether_contact, tether_release: A skin particle in contact in a step (within the
            detection margin of another part of the skin:
            :attr:`~warpskin.model.Contacts.colliding`) reaches ``e = tether_contact -
            tether_max`` (x the diagonal, at least 0) farther: its tether radius and its cap
            grow by ``e``. Where LBS drives one part into another (a leg into the belly), the
            contacts push the skin farther from LBS than the tether lets it swing, and a tether
            that pulled it back pulled it into the crossing. Once the contact ends, the reach
            shrinks to 0 over ``tether_release`` seconds (``State.contact_reach``), so that the
            tether takes the skin back smoothly rather than in one step. Only on a character
            whose simulated skin has no intersecting pair at rest
            (:func:`~warpskin.solver.clean_at_rest`): where pieces cross at rest the contacts
            start inside what they should keep apart. Keep ``tether_contact`` below
            ``max_offset``.
        chord_strain, chord_area: A refined skin (a coarse mesh simulated on a refined copy,
            written with its own triangles: chords of the simulated surface) keeps its written
            edges within ``chord_strain`` of their rest length (or of LBS's, where LBS strains
            them more) and its written triangles facing the way LBS faces them with at least
            ``chord_area`` of their LBS area (:mod:`warpskin.kernels.chords`), once per
            elasticity iteration and again before the volume loop; 0 turns either off. Only a
            refined skin with volume constraints has them.
    """

    _section = "solver"

    iterations: int = setting(20, "integer", "elasticity iterations per step", low=1, cli="--iterations")
    volume_iterations: int = setting(4, "integer", "volume iterations per step", low=0, cli="--volume-iterations")
    rotation_iterations: int = setting(1, "integer", "warm-started rotation-extraction iterations per region fit",
                                       low=1)
    dt: float = setting(0.005, "number", "largest substep", unit="s", low=0.0, open_low=True, must="a positive number",
                        cli="--dt")
    gravity: tuple[float, float, float] = setting((0.0, -9.81, 0.0), "numbers", "external acceleration", unit="m/s^2",
                                                  length=3, must="three finite numbers")
    units: str = setting("auto", "string", "the file's length unit for gravity: auto (the power of ten of the metre "
                         "that makes the character nearest human size) or file (metres)", choices=("auto", "file"))
    damping: float = setting(2.0, "number", "velocity damping rate", unit="1/s", low=0.0, must="a rate >= 0",
                             cli="--damping")
    fast_summation: bool = setting(False, "bool", "region sums by prefix scans along paths (false: direct gather)",
                                   cli="--fast-summation")
    volume_along_normals: bool = setting(False, "bool", "volume corrections along the surface normals, inverse "
                                         "masses floored at the median")
    volume_stiffness: float = setting(1.0, "number", "stiffness of the volume constraints", low=0.0, high=1.0,
                                      must="in [0, 1]")
    tether: float = setting(1.5, "number", "the farthest a particle may be from its LBS target, x its tissue depth "
                            "(0: off)", low=0.0)
    tether_floor: float = setting(0.01, "number", "added to the tether radius, x the body's diagonal", low=0.0)
    tether_max: float = setting(0.05, "number", "no tether radius is longer than this, x the body's diagonal",
                                low=0.0)
    tether_contact: float = setting(0.07, "number", "the cap of a skin particle in contact, x the body's diagonal "
                                    "(contacts push the skin past the tether)", low=0.0)
    tether_release: float = setting(0.25, "number", "seconds in which a particle's contact cap shrinks back to "
                                    "tether_max once its contact ends", low=0.0, open_low=True)
    chord_strain: float = setting(1.4, "number", "a refined skin's written edges stay within this strain of their "
                                  "rest length, or of LBS's where LBS strains them more (0: off)", low=0.0,
                                  must="0 (off) or > 1")
    chord_area: float = setting(0.1, "number", "a refined skin's written triangles keep at least this share of their "
                                "LBS area facing the way LBS faces them (0: off)", low=0.0, high=1.0,
                                open_high=True, must="in [0, 1)")
    def check(self, where: str = "SolverParams") -> None:
        """Every setting in its declared range (:func:`~warpskin.settings.check_settings`).

        Raises:
            SceneError: ``"<where>: [solver] <key> must be <range>, got <value>"``.
        """
        check_settings(self, where, "solver")
        if 0.0 < self.chord_strain <= 1.0:
            raise SceneError(f"{where}: [solver] chord_strain must be 0 (off) or > 1, got {self.chord_strain:g}")


@dataclass(frozen=True)
class RunLimits:
    """The plausible range of a run (keys of the scene's ``[solver]`` section): a frame out of it
    stops the run (:class:`~warpskin.errors.SimulationError`, the frames before it kept) unless
    the run allows it (``allow_unstable``); the solver never reads them.

    Attributes:
        max_offset: A run stops (SimulationError) at the first frame whose skin is farther
            than this fraction of the body's diagonal from LBS.
        max_volume_error: A run stops at the first frame whose volume (whole or any
            sub-volume) is off its rest volume by more than this fraction, more than twice LBS's
            error in that frame and more than LBS's worst error in any frame so far (an
            animation whose LBS loses a third of the neck's volume as the head folds down shows
            that such a change belongs to it; the physics, holding the volume, lags LBS's
            recovery by a few frames). A sub-volume's error is a share of its rest volume or of
            a hundredth of the body's, where it is smaller
            (:attr:`~warpskin.preprocess.sub_volumes.SubVolumes.error_scale`).
        max_speed: A run stops at the first frame where the skin's motion relative to the
            animation (its velocities minus LBS's, mass-weighted RMS) is faster than this many
            body diagonals per second and grew, since the frame before, by more than the
            animation's own change of velocity over the frame (mass-weighted RMS): energy the
            animation did not put in. A skin lagging a sudden start or stop (a jump, a punch)
            moves fast relative to it, by no more than that change.
        max_strained: A run stops at the first frame where a written mesh has more of its edges
            strained past 1.5x of their rest length (or under 1/1.5) than its own LBS by more
            than this share (:mod:`warpskin.quality`).
        max_flipped: A run stops at the first frame where more than this share of a written
            mesh's triangles turn by more than 90 degrees against its LBS.
        max_capped: A run stops at the first frame where more than this share of the simulated
            skin has been held at the tether's cap (``tether_max``) in every frame of the last
            ``capped_time`` seconds: the cap would hide an explosion.
        capped_time: See ``max_capped``. A skin lagging a sudden start or stop (a punch, a
            flex in a few hundredths of a second) reaches the cap for a frame and comes back;
            an explosion the cap holds stays there. 0: the first such frame stops the run.
    """

    _section = "solver"

    max_offset: float = setting(0.1, "number", "a frame farther than this from LBS (x the diagonal) stops the run",
                                low=0.0)
    max_volume_error: float = setting(0.1, "number", "a frame whose volume or a sub-volume's is off by more than this "
                                      "share stops the run", low=0.0)
    max_speed: float = setting(2.0, "number", "skin motion relative to LBS faster than this, and growing by more "
                               "than the animation's own change of velocity, stops the run", unit="diagonals/s",
                               low=0.0)
    max_strained: float = setting(0.05, "number", "a written mesh with this share more strained edges than its LBS "
                                  "stops the run", low=0.0)
    max_flipped: float = setting(0.05, "number", "a written mesh with more than this share of its triangles turned "
                                 "over against LBS stops the run", low=0.0)
    max_capped: float = setting(0.1, "number", "more than this share of the skin held at the tether's cap for "
                                "capped_time stops the run", low=0.0)
    capped_time: float = setting(0.1, "number", "how long more than max_capped of the skin must stay at the "
                                 "tether's cap to stop the run (0: one frame)", unit="s", low=0.0)

    def check(self, where: str = "RunLimits") -> None:
        """Every setting in its declared range (:func:`~warpskin.settings.check_settings`).

        Raises:
            SceneError: ``"<where>: [solver] <key> must be <range>, got <value>"``.
        """
        check_settings(self, where, "solver")


@dataclass(frozen=True)
class CollisionParams:
    """Self-collision settings (a scene's ``[collision]``). Each field's kind, default, range,
    unit and help are declared with it (:mod:`warpskin.settings`): the checks, the scene keys and
    the docs' reference are made from that. Notes beyond the one-line help:

    * ``detection_margin``: detection runs once per step; pairs that close in during the
      constraint loop must already be listed.
    * ``rest_gap_margin``: side by side on a smooth surface, vertices of one patch are closer than
      the thickness; their pairs become contacts only when they cross during a step (a fold).
    * ``rebuild_spread``: the tree is refit every step; a refit keeps the rest pose's topology,
      whose boxes overlap more and more as limbs swing, so it is rebuilt (in place, between
      frames) past this deformation (vertex displacements less their mean).
    * ``volume_weight``: Diziol et al. 2011 use 0 (colliding particles stay put); then a part
      whose skin is all in contact (a paw that LBS passes through the other leg) cannot keep its
      volume at all and turns inside out. A small weight keeps both that volume and a bent
      joint's crease free of intersections; larger ones let the volume loop push contacts through.
    * ``fail_safe_rounds``: after the elasticity loop of every step, pairs of the skin's
      triangles as written that intersect, did not at the start of the step and do not under LBS
      are found exactly and their vertices put back where they started (carried along by their
      bones, held where that still intersects; :meth:`SelfCollision.fail_safe`). The constraints
      alone miss a vertex that slides into a neighbouring triangle from behind its plane or runs
      past the search radius in the constraint loop. A second pass after the volume loop holds
      what that loop pushed through where the loop found it, and the loop runs again with those
      vertices pinned.
    """

    _section = "collision"

    enabled: bool = setting(True, "bool", "detect and resolve skin self-collisions", cli="--no-collisions",
                            cli_help="switch skin self-collision off")
    thickness: float | None = setting(None, "number", "contact thickness; automatic: 0.15 x the mean skin edge",
                                      unit="m", low=0.0, open_low=True, optional=True, must="a positive length [m]")
    friction: float = setting(0.3, "number", "Coulomb friction coefficient of the contacts", low=0.0, must=">= 0")
    restitution: float = setting(0.0, "number", "restitution coefficient of the contacts", low=0.0, high=1.0,
                                 must="in [0, 1]")
    capacity: int = setting(4096, "integer", "initial contact candidates per kind (the buffers grow on overflow)",
                            low=1, must="a positive integer")
    rigid_weight: float = setting(0.999, "number", "a vertex with at least this weight on one bone moves rigidly with "
                                  "it; two such vertices of one bone never collide", low=0.0, high=1.0, open_low=True,
                                  must="in (0, 1]")
    detection_margin: float = setting(3.0, "number", "candidates are searched within this many thicknesses", low=1.0,
                                      must=">= 1 (times the thickness)")
    rest_gap_margin: float = setting(2.0, "number", "vertices closer than this many search radii at rest are one "
                                     "surface patch (they collide only across a fold)", low=0.0, must=">= 0")
    fold_cos: float = setting(0.0, "number", "pairs of one patch whose normals are more than acos(fold_cos) apart "
                              "face each other across a fold", low=-1.0, high=1.0, must="in [-1, 1]")
    rebuild_spread: float = setting(0.1, "number", "the tree is rebuilt once the skin has deformed by more than this "
                                    "share of its rest diagonal", low=0.0, open_low=True, must="> 0")
    passes: int = setting(4, "integer", "Jacobi passes over the contacts per elasticity iteration", low=1,
                          must="an integer >= 1")
    volume_weight: float = setting(0.05, "number", "factor on a colliding particle's inverse mass in the volume loop",
                                   low=0.0, high=1.0, must="in [0, 1]")
    fail_safe_rounds: int = setting(4, "integer", "rounds of the fail-safe that puts back pairs the constraints let "
                                    "through (0: off)", low=0, must="an integer >= 0")

    def check(self, where: str = "model") -> None:
        """Every setting in its declared range (:func:`~warpskin.settings.check_settings`).

        Raises:
            SceneError: ``"<where>: [collision] <key> must be <range>, got <value>"``.
        """
        check_settings(self, where, "collision")


@dataclass
class PoppingSettings:
    """The ``[popping]`` section of a scene.

    Attributes:
        mode: ``"goal"``: the paper's goal-seeking skin; ``"layered"``: the activation moves the
            muscle layer's rest shape of the multi-layer model toward the clenched example (or
            the swelling of a muscle found from the skeleton) and the physical skin (shape
            matching, volume, collisions) makes the pop; ``None``: goal where the scene has
            examples, else layered.
        alpha_min: Stiffness at the largest disparity, in (0, 1] (eq. 3).
        beta: Relaxation rate [1/s] (eq. 4).
        threshold: Snap distance of relaxing vertices [m].
        dt: Step length [s]; ``None``: one step per frame.
        rbf_width: Gaussian width in pose space [rad]; ``None``: automatic.
        joints: Joints spanning pose space; ``None``: the joints the examples vary.
        activation: Activation per muscle group over clip time.
    """

    _section = "popping"

    mode: str | None = setting(None, "string", "goal: the paper's goal-driven skin; layered: the activation drives "
                               "the multi-layer model's muscle layer (default: goal where the scene has examples, "
                               "else layered)", choices=("goal", "layered"), optional=True, cli="--mode")
    alpha_min: float = setting(0.1, "number", "stiffness at the largest disparity (eq. 3)", low=0.0, high=1.0,
                               open_low=True, must="in (0, 1]", cli="--alpha-min")
    beta: float = setting(30.0, "number", "relaxation rate (eq. 4)", unit="1/s", low=0.0, open_low=True,
                          must="a positive relaxation rate", cli="--beta")
    threshold: float = setting(1e-4, "number", "snap distance of relaxing vertices", unit="m", low=0.0,
                               must="a distance >= 0")
    dt: float | None = setting(None, "number", "step length (default: one step per frame)", unit="s", low=0.0,
                               open_low=True, optional=True, must="a positive step length", cli="--dt")
    rbf_width: float | None = setting(None, "number", "Gaussian width in pose space (default: automatic)", unit="rad",
                                      low=0.0, open_low=True, optional=True, must="a positive angle")
    joints: list[str] | None = setting(None, "strings", "the joints spanning pose space (default: those the examples "
                                       "vary)", optional=True)
    activation: ActivationTimeline = setting(
        _no_activation, "table", "activation per muscle group over clip time: [popping.activation.GROUP] keys = "
        "[[t, a], ...] or beats = [t, ...] with hold (attack, release) [s]")
    examples: dict | None = setting(None, "table", "the rig file's blend shapes as examples: clip, normal = [...], "
                                    "clenched = {GROUP = [...]}", optional=True)

    def check(self, where: str = "scene") -> None:
        """Every setting in its declared range, and ``beta * dt <= 1``.

        Raises:
            SceneError: ``"<where>: [popping] <key> must be <range>, got <value>"``.
        """
        check_settings(self, where, "popping")
        if self.dt is not None and self.beta * self.dt > 1.0 + 1e-12:
            raise SceneError(f"{where}: [popping] beta * dt = {self.beta * self.dt:.4g} must be <= 1 (no overshoot on "
                             f"relax); lower beta or dt")
