"""The one update step, pure.

The state, the plans of absorb, add, merge, remove and finalize, the core step with
its truncation, and the guaranteed error bound.
"""

from streamsvd._util.lazy import lazy_exports

# public name -> the submodule that defines it (imported on first access)
_EXPORTS = {
    "Bound": "bound",
    "CoreStep": "core",
    "core_step": "core",
    "Downdate": "downdate",
    "Ledger": "downdate",
    "plan_remove": "downdate",
    "HISTORY_FIELDS": "record",
    "UpdateRecord": "record",
    "RightFactor": "rows",
    "RowAppend": "rows",
    "RowFactor": "rows",
    "Plan": "state",
    "State": "state",
    "StepOptions": "state",
    "Writes": "state",
    "apply_plan": "state",
    "stage_plan": "state",
    "plan_absorb": "update",
    "plan_add": "update",
    "plan_finalize": "update",
    "plan_merge": "update",
    "ERROR_MEASURES": "truncation",
    "Before": "truncation",
    "Truncation": "truncation",
    "error_budget": "truncation",
    "plan_absorb_by_gram": "update_gram",
    "plan_merge_by_gram": "update_gram",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
