"""The node's service and action callbacks: ``~/explain``, ``~/recommend_settings`` (service and action with
feedback and cancel), ``~/reset_reference``. Thin: the answers are :class:`~xmetro_ros.ros.core.XmetroCore`'s.

A mixin of the node's wiring (:class:`xmetro_ros.ros.node.XmetroWiring`).
"""

from __future__ import annotations

from typing import Any

from std_srvs.srv import Trigger

from ..action import RecommendSettings as RecommendSettingsAction
from ..srv import Explain, RecommendSettings
from .convert import mm_to_m
from .core import XmetroCore
from .diagnostics import DiagnosticsState
from .rclpy_util import NodeMixin

__all__ = ["ServiceHandlers"]


class ServiceHandlers(NodeMixin):
    """Service and action callbacks of the node (see the module docstring)."""

    core: XmetroCore | None
    diag: DiagnosticsState | None

    def _on_explain(self, req: Explain.Request, resp: Explain.Response) -> Explain.Response:
        assert self.core is not None
        out = self.core.explain(req)
        if not out.success:
            self.get_logger().warning(f"~/explain refused: {out.message}")
        return out

    def _on_recommend(self, req: RecommendSettings.Request, resp: RecommendSettings.Response) -> Any:
        assert self.core is not None
        out = self.core.recommend(req)
        if not out.success:
            self.get_logger().warning(f"~/recommend_settings refused: {out.message}")
        return out

    def _execute_recommend(self, goal: Any) -> Any:
        """``~/recommend_settings`` action: the service's search with feedback; cancel → CANCELED, a refused
        request → ABORTED (result success false, message says why)."""
        from ..plan.recommend import RecommendCancelled, RecommendProgress

        result = RecommendSettingsAction.Result()
        core = self.core
        if core is None:
            goal.abort()
            result.message = "the node is not configured"
            return result
        fb = RecommendSettingsAction.Feedback()

        def progress(p: RecommendProgress) -> None:
            fb.orientations_evaluated, fb.orientations_total = p.evaluated, p.total
            fb.orientations_kept, fb.settings_per_orientation = p.kept, p.n_settings
            fb.elapsed = float(p.elapsed_s)
            fb.best_p95_abs_error = float(mm_to_m(float(p.best_p95_mm)))  # inf stays inf
            goal.publish_feedback(fb)

        try:
            out = core.recommend(goal.request, progress, lambda: goal.is_cancel_requested)
        except RecommendCancelled as e:
            goal.canceled()
            result.message = str(e)
            result.model_id = core.model_id
            return result
        for name in RecommendSettings.Response.get_fields_and_field_types():
            setattr(result, name, getattr(out, name))
        if out.success:
            goal.succeed()
        else:
            self.get_logger().warning(f"~/recommend_settings action refused: {out.message}")
            goal.abort()
        return result

    def _on_reset_reference(self, req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        core = self.core
        if core is None or core.reference is None:
            resp.success, resp.message = False, "no reference sphere configured (reference_radius 0)"
            return resp
        core.reference.reset()
        if self.diag is not None:
            self.diag.on_reference_reset()
        self.get_logger().info("reference stream reset: the next reference scans set the in-control level anew")
        resp.success, resp.message = True, "reference drift monitor reset"
        return resp
