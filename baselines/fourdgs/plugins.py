"""Plugin base class and registry.

A plugin is a subclass of `Plugin` that overrides the hook methods it needs (see hooks.py for the
order in which the trainer calls them). Plugins are found in two places:

1. the entry-point group ``fourdgs.plugins`` of installed distributions (setup.cfg:
   ``[options.entry_points] fourdgs.plugins = reflow = reflow_plugin.plugin:ReFlowPlugin``), the
   way nerfstudio discovers methods;
2. an in-process registry (`register_plugin`), for development checkouts and tests.

An unknown name is an error listing what exists. Components (`Plugin.components`) are the
plugin's switchable parts, toggled with ``--disable a,b`` / ``--enable a,b`` (the ablation rows).
"""
from __future__ import annotations

import logging
from importlib import metadata
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Mapping

if TYPE_CHECKING:  # imports for annotations only; the host modules import this one
    from torch import Tensor

    from baselines.data import PointCloud

    from .gaussian_model import GaussianModel
    from .hooks import TrainContext, ViewRender

ENTRY_POINT_GROUP = "fourdgs.plugins"
log = logging.getLogger(__name__)


class PluginError(ValueError):
    """Unknown plugin, bad plugin definition, or bad component toggles."""


class Plugin:
    """Base class of host plugins. Every hook is a no-op here; override what you need.

    Class attributes:
        name: registry name (``--plugin NAME``).
        components: switchable parts, in the order of the plugin's ablation table.
        default_disabled: components off unless ``--enable``d.
        param_groups: config groups the plugin adds, {group name: dataclass}; they are settable
            from config files (``ReFlowParams = dict(...)``) and the command line like 4DGS's.
        outputs: names of the files/folders the plugin writes in the model folder (what
            ``--overwrite`` clears besides the host's outputs; anything else is kept).
    Instance attributes set by the host: ``params`` ({group name: dataclass instance}) and
    ``enabled`` (the frozenset of active components).
    """

    name: ClassVar[str] = ""
    components: ClassVar[tuple[str, ...]] = ()
    default_disabled: ClassVar[tuple[str, ...]] = ()
    param_groups: ClassVar[dict[str, type]] = {}
    outputs: ClassVar[tuple[str, ...]] = ()

    def __init__(self, params: Mapping[str, Any] | None = None, enabled: frozenset[str] | None = None) -> None:
        self.params = dict(params or {})
        self.enabled = frozenset(self.components) - frozenset(self.default_disabled) if enabled is None else enabled

    def min_train_frames(self) -> tuple[int, str]:
        """(training frames this plugin needs with its enabled components, what needs them); the host
        checks it right after loading the scene, and names it in an empty-split error."""
        return 1, ""

    def is_enabled(self, component: str) -> bool:
        if component not in self.components:
            raise PluginError(f"plugin {self.name!r} has no component {component!r}; it has {list(self.components)}")
        return component in self.enabled

    # --- set-up hooks -----------------------------------------------------------------------
    def on_scene_loaded(self, ctx: TrainContext) -> None:
        """The dataset is loaded (ctx.scene); validate plugin inputs here, before long work."""

    def initial_point_cloud(self, ctx: TrainContext) -> PointCloud | None:
        """Return a point cloud to replace the host's initial one (ctx.point_cloud), or None."""
        return None

    def build_model(self, ctx: TrainContext) -> GaussianModel | None:
        """Return a GaussianModel (e.g. with another deformation module) to replace the host's."""
        return None

    def on_model_created(self, ctx: TrainContext) -> None:
        """ctx.model exists (initialised from the cloud, or loaded): register per-Gaussian buffers."""

    def on_stage_start(self, ctx: TrainContext) -> None:
        """A stage ("coarse" or "fine") starts; ctx.model.optimizer has just been (re)built."""

    # --- per-iteration hooks ----------------------------------------------------------------
    def select_batch(self, ctx: TrainContext) -> list | None:
        """Return the cameras of this iteration's batch (e.g. neighbouring frame pairs), or None."""
        return None

    def select_partners(self, ctx: TrainContext) -> list | None:
        """Cameras to deform and project (not composite) next to the batch, or None.

        Their ViewRender land in ctx.partners (same order), before `extra_features`, so a view's
        channels can be built from a partner's projection (e.g. flow towards a neighbouring frame)
        without rendering it. Partners take no part in the baseline loss or densification.
        """
        return None

    def partner_rows(self, ctx: TrainContext) -> list[Tensor | None] | None:
        """Per camera of `select_partners` (same order): [N] bool, the Gaussians whose state at its
        time the plugin will read, or None (all); None for all partners.

        The deformation module may leave the other rows of that partner undeformed (canonical), which
        saves their deformation: e.g. ReFlow reads a partner's projection only through flow channels
        of a batch view, so a Gaussian the view cannot show is not needed at the partner's time.
        """
        return None

    def partner_shared_rows(self, ctx: TrainContext) -> list[tuple[int, Tensor] | None] | None:
        """Per camera of `select_partners` (same order): (k, [N] bool) or None; None for all partners.

        The Gaussians in the mask take, at the partner, their state at batch view k's time (values,
        and gradients through that view's deformation) instead of being deformed to the partner's
        time (`GaussianModel.deform_many`'s `shared`): e.g. ReFlow's static field read once, at the
        view's time, so a static Gaussian's flow towards the partner is the camera's alone.
        """
        return None

    def extra_features(self, ctx: TrainContext, view_index: int) -> dict[str, Tensor] | None:
        """Per-Gaussian feature channels to composite in view `view_index`'s pass.

        All views of the batch are deformed and projected before any is composited, so
        ctx.views[k].state and ctx.views[k].projection are available for every k.
        Returns {name: [N, c]}; the maps come back as ctx.views[view_index].extras[name] [H,W,c].
        """
        return None

    def loss_weights(self, ctx: TrainContext, view_index: int) -> Tensor | None:
        """Per-pixel weights [H, W, 1] of view `view_index` in the baseline photometric loss, or None.

        Called after compositing. The host multiplies the weights of all plugins; L1 and D-SSIM
        become weighted means (an all-ones map gives the unweighted loss). E.g. leave out
        pixels of moving objects while a model of the static scene is fitted.
        """
        return None

    def extra_losses(self, ctx: TrainContext) -> dict[str, Tensor] | None:
        """Loss terms to add to ctx.losses (already weighted); names are prefixed with the plugin's."""
        return None

    def pre_backward(self, ctx: TrainContext) -> None:
        """Called with the total loss in ctx.loss, before backward."""

    def post_backward(self, ctx: TrainContext) -> None:
        """Gradients exist; the optimizer has not stepped and densification has not run."""

    def protected_gaussians(self, ctx: TrainContext) -> Tensor | None:
        """[N] bool: Gaussians densification must not prune this iteration (None: protect none).

        Called before densification; the host ORs the masks of all plugins. Protected Gaussians
        are still cloned, split and opacity-reset; only removal is skipped. E.g. keep Gaussians
        whose motion is not learned yet from being pruned as transparent.
        """
        return None

    def post_densify(self, ctx: TrainContext) -> None:
        """Densification ran this iteration (ctx.densify_record says what it did)."""

    def on_iteration_end(self, ctx: TrainContext) -> None:
        """The optimizer stepped."""

    def on_stage_end(self, ctx: TrainContext) -> None:
        """A stage finished."""

    # --- persistence ------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Plugin state stored in full training checkpoints (chkpnt_*.pth)."""
        return {}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore what `state_dict` returned."""

    def on_save(self, ctx: TrainContext, point_cloud_dir: Any) -> None:
        """A point_cloud/iteration_N directory was written; add the plugin's own files to it."""

    def on_load(self, ctx: TrainContext, point_cloud_dir: Any) -> None:
        """A point_cloud/iteration_N directory was loaded into ctx.model (resume or upgrade)."""

    # --- viewer -----------------------------------------------------------------------------
    def viewer_modes(self) -> dict[str, Callable[..., Any]]:
        """Extra render modes of the web viewer (view.py): {name: fn(frame) -> (picture, caption)},
        frame a `baselines.viewer.frame.ViewFrame`, picture [H, W, 3] uint8 RGB, caption a short str."""
        return {}


_LOCAL_REGISTRY: dict[str, Callable[[], type[Plugin]]] = {}


def register_plugin(cls: type[Plugin]) -> type[Plugin]:
    """Class decorator adding a plugin to the in-process registry (overrides an entry point)."""
    if not (isinstance(cls, type) and issubclass(cls, Plugin)) or not cls.name:
        raise PluginError(f"{cls!r} must be a Plugin subclass with a non-empty `name`")
    _LOCAL_REGISTRY[cls.name] = lambda: cls
    return cls


def unregister_plugin(name: str) -> None:
    _LOCAL_REGISTRY.pop(name, None)


def _entry_points() -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def available_plugins() -> dict[str, str]:
    """{name: where it comes from} for every discoverable plugin."""
    found = {name: f"entry point {ep.value}" for name, ep in _entry_points().items()}
    found.update({name: "registered in-process" for name in _LOCAL_REGISTRY})
    return dict(sorted(found.items()))


def load_plugin_class(name: str) -> type[Plugin]:
    """Resolve a plugin name to its class.

    Raises:
        PluginError: unknown name (listing the available ones) or an entry point that does not
            resolve to a Plugin subclass.
    """
    if name in _LOCAL_REGISTRY:
        cls = _LOCAL_REGISTRY[name]()
    else:
        eps = _entry_points()
        if name not in eps:
            known = ", ".join(available_plugins()) or "none"
            raise PluginError(f"unknown plugin {name!r}; available plugins: {known}")
        try:
            cls = eps[name].load()
        except Exception as exc:
            raise PluginError(f"plugin {name!r} ({eps[name].value}) failed to import: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Plugin)):
        raise PluginError(f"plugin {name!r} does not resolve to a Plugin subclass (got {cls!r})")
    return cls


def resolve_components(
    plugin_classes: list[type[Plugin]], disable: list[str], enable: list[str]
) -> dict[str, frozenset[str]]:
    """Apply --disable/--enable to the plugins' components.

    Returns:
        {plugin name: enabled components}.
    Raises:
        PluginError: a name that no loaded plugin declares (listing those that exist), or a name
            both enabled and disabled.
    """
    owners: dict[str, str] = {}
    for cls in plugin_classes:
        for comp in cls.components:
            owners[comp] = cls.name
    both = sorted(set(disable) & set(enable))
    if both:
        raise PluginError(f"components both enabled and disabled: {both}")
    for comp in [*disable, *enable]:
        if comp not in owners:
            known = ", ".join(f"{c} ({p})" for c, p in owners.items()) or "none (no plugin with components is loaded)"
            raise PluginError(f"unknown component {comp!r}; available components: {known}")
    result = {}
    for cls in plugin_classes:
        active = set(cls.components) - set(cls.default_disabled)
        active |= {c for c in enable if owners[c] == cls.name}
        active -= {c for c in disable if owners[c] == cls.name}
        result[cls.name] = frozenset(active)
    return result
