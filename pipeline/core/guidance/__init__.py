"""Guidance: laws that turn the navigated state and a target into a thrust command (GuidanceLaw).

`GUIDANCE_LAWS` maps a law's kind to its class; each class is built as `Law(options, vehicle)`
with its options class beside it (`OPTIONS[kind]`)."""

from pipeline.core.guidance.apollo import ApolloGuidance, ApolloOptions
from pipeline.core.guidance.base import GuidanceLaw, NavigatedState, Target, ThrustCommand
from pipeline.core.guidance.constant import ConstantThrust, ConstantThrustOptions

GUIDANCE_LAWS: dict[str, type] = {ConstantThrust.kind: ConstantThrust,
                                  ApolloGuidance.kind: ApolloGuidance}
OPTIONS: dict[str, type] = {ConstantThrust.kind: ConstantThrustOptions,
                            ApolloGuidance.kind: ApolloOptions}

__all__ = ["GUIDANCE_LAWS", "OPTIONS", "ApolloGuidance", "ApolloOptions", "ConstantThrust",
           "ConstantThrustOptions", "GuidanceLaw", "NavigatedState", "Target", "ThrustCommand"]
