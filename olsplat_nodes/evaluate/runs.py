"""What ``olsplat eval`` runs: one aggregation per (method, encoders, fusion weights, 3D branch).

Three kinds, one per group of the paper's tables:
- ``method``: the aggregation methods on the chosen features (Tables 2-5 and the component
  ablation);
- ``feature``: the full method on each 2D encoder alone, the 2D fusion without the 3D branch
  and the 2D-3D fusion, once with the geometric descriptors and once with the MinkUNet (the
  given checkpoint, else the shipped self-supervised one) as point features (Table 6);
- ``sweep``: the full method with the 3D branch over lambda_2D x lambda_f (Table 7).
Runs with identical settings are aggregated once and reported under every label they carry.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ..encoders.spec import DEFAULT_SPEC
from ..structure.branch import SHIPPED_MINKUNET, StructureConfig

LAMBDA_2D = (0.5, 0.6, 0.7, 1.0)  # 1.0: the first encoder (cnn64) alone
LAMBDA_F = (0.6, 0.7, 0.8)
WITHOUT_3D = "w/o 3D fusion"  # Table 6's reference: the paired differences are taken against it
FUSED_DESCRIPTORS = "2D-3D fusion (descriptors)"
FUSED_MINKUNET = "2D-3D fusion (MinkUNet)"


@dataclass(frozen=True)
class Run:
    label: str
    kind: str  # "method", "feature" or "sweep"
    method: str
    encoders: str  # encoder spec (shipped names, "shipped" for both fused, or folders)
    weights: tuple[float, ...] | None  # lambda_2D fusion weights; None = the spec's default
    structure: StructureConfig | None  # the 3D branch, or None for 2D features only

    @property
    def settings(self) -> tuple:
        return (self.method, self.encoders, self.weights, self.structure)

    def describe(self) -> dict:
        return {
            "kind": self.kind,
            "method": self.method,
            "encoders": self.encoders,
            "weights": list(self.weights) if self.weights else None,
            "features": "2d3d" if self.structure else "2d",
            "lambda_f": self.structure.lambda_f if self.structure else None,
            "minkunet": str(self.structure.minkunet) if self.structure and self.structure.minkunet else None,
        }


def plan_runs(
    methods: list[str],
    encoders: str = DEFAULT_SPEC,
    weights: tuple[float, ...] | None = None,
    with_3d: bool = False,
    feature_ablation: bool = False,
    fusion_sweep: bool = False,
    structure: StructureConfig = StructureConfig(),
) -> list[Run]:
    main_structure = structure if with_3d else None
    runs = [Run(m, "method", m, encoders, weights, main_structure) for m in methods]
    if feature_ablation:
        if "," in encoders:
            members = encoders.split(",")
        else:  # the shipped ones (the default is one of them): each alone beside the given spec
            from ..encoders.shipped import SHIPPED

            members = list(SHIPPED) if encoders in ("shipped", *SHIPPED) else [encoders]
        runs += [Run(name, "feature", "outlangsplat", name, None, None) for name in members]
        runs.append(Run(WITHOUT_3D, "feature", "outlangsplat", encoders, weights, None))
        descriptors = replace(structure, minkunet=None)
        minkunet = structure if structure.minkunet is not None else replace(structure, minkunet=SHIPPED_MINKUNET)
        runs.append(Run(FUSED_DESCRIPTORS, "feature", "outlangsplat", encoders, weights, descriptors))
        runs.append(Run(FUSED_MINKUNET, "feature", "outlangsplat", encoders, weights, minkunet))
    if fusion_sweep:
        for l2d in LAMBDA_2D:
            for lf in LAMBDA_F:
                label = f"lambda_2D={l2d} lambda_f={lf}"
                runs.append(
                    Run(
                        label,
                        "sweep",
                        "outlangsplat",
                        encoders,
                        (l2d, round(1 - l2d, 6)),
                        replace(structure, lambda_f=lf),
                    )
                )
    return runs
