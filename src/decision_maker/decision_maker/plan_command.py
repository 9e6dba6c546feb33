"""``plan_command``: show the plan a command would get, without moving anything (dry run).

No ROS needed: the known objects come from a map (default: the bundled sample map) or a list;
the object memory is the one a freshly started object database would have (the map's instances),
so plans go to where each object is (``--holding`` says what the robot holds)::

    ros_run decision_maker plan_command "give me the cup please"
    ros_run decision_maker plan_command "I'm thirsty" --planner tiered --llm-url http://127.0.0.1:11434/v1 \\
        --llm-model llama3.2
    ros_run decision_maker plan_command "bring me the mug" --objects mug,plate --json

Exit code: 0 a plan was made or a question answered, 1 refused (reason printed; also a "did you
mean ...?" or a "which one?"), 2 bad arguments/configuration.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from decision_maker.command_types import MAX_TEXT_CHARS, load_locations, sanitize_text
from decision_maker.errors import ConfigError, PlanningError, Reply
from decision_maker.memory.world import aliases_for
from decision_maker.nl_planner import PlanningContext, RegistryPlanner
from decision_maker.planning.llm_planner import TIERS, LLMConfig, LLMPlanner, TieredPlanner
from object_query.errors import ObjectQueryError
from object_query.memory import Belief, MapObservation, ObjectMemory


def known_objects(args: argparse.Namespace) -> tuple[dict[str, tuple[float, float, float]], tuple[Belief, ...]]:
    """Object names with positions, and the memory built from the map (empty for ``--objects``)."""
    if args.objects is not None:
        return {n.strip().lower(): (0.0, 0.0, 0.0) for n in args.objects.split(",") if n.strip()}, ()
    from object_query.semantic_map import ObjectDatabase

    if args.map:  # its class table: --semantic, else the semantic.json beside it
        map_path = args.map
        sem_path = args.semantic or os.path.join(os.path.dirname(os.path.abspath(args.map)), "semantic.json")
    else:
        from object_query.object_query_server import bundled_map_paths

        map_path, sem_path = bundled_map_paths()
    db = ObjectDatabase.from_files(map_path, sem_path)
    out = {}
    for name in db.names():
        res = db.query(name)
        out[name] = res.position
    memory = ObjectMemory()
    memory.merge_map(MapObservation(i.name, i.centre) for i in db.all_instances())
    return out, memory.snapshot()


def synonym_groups() -> tuple[tuple[str, ...], ...]:
    """The object database's bundled synonyms (none when not installed)."""
    try:
        from object_query.names import load_synonyms
        from object_query.object_query_server import bundled_synonyms_path

        return load_synonyms(bundled_synonyms_path()).groups
    except Exception:  # only a help for names
        return ()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="plan_command", description="Dry run: print the plan for a command.")
    ap.add_argument("text", nargs="+", help="the command, e.g. give me the cup")
    ap.add_argument("--planner", choices=("registry", "llm", "tiered"), default="registry")
    ap.add_argument("--tier", choices=TIERS, default="registry_first", help="with --planner tiered")
    ap.add_argument("--llm-url", default=LLMConfig.base_url)
    ap.add_argument("--llm-model", default=LLMConfig.model)
    ap.add_argument("--llm-timeout", type=float, default=LLMConfig.timeout_s)
    ap.add_argument("--locations", default="", help="locations YAML (default: the installed one)")
    ap.add_argument("--map", default="", help="params.npz for the known objects (default: bundled sample map)")
    ap.add_argument("--semantic", default="", help="the class table of --map (default: semantic.json beside it)")
    ap.add_argument("--objects", default=None, help="comma-separated object names instead of a map")
    ap.add_argument("--holding", default=None, help="object the robot holds now")
    ap.add_argument("--json", action="store_true", help="print the plan as JSON")
    args = ap.parse_args(argv)
    text = sanitize_text(" ".join(args.text))
    if not text or len(text) > MAX_TEXT_CHARS:
        print(f"error: the command must have 1..{MAX_TEXT_CHARS} characters", file=sys.stderr)
        return 2
    try:
        if args.locations:
            locations = load_locations(args.locations)
        else:
            from decision_maker.decision_maker_node import default_locations_file

            locations = load_locations(default_locations_file())
        objects, memory = known_objects(args)
        cfg = LLMConfig(base_url=args.llm_url, model=args.llm_model, timeout_s=args.llm_timeout)
        if args.planner == "registry":
            planner = RegistryPlanner()
        elif args.planner == "llm":
            planner = LLMPlanner(cfg)
        else:
            planner = TieredPlanner(LLMPlanner(cfg), tier=args.tier)
    except (ConfigError, OSError, ValueError, ObjectQueryError) as exc:  # ObjectQueryError: a map it cannot load
        print(f"error: {exc}", file=sys.stderr)
        return 2
    aliases = aliases_for(objects, synonym_groups())
    context = PlanningContext(frozenset(objects), locations, objects, held_object=args.holding, memory=memory,
                              aliases=aliases)
    try:
        plan = planner.plan(text, context)
    except Reply as reply:  # a question, or a "did you mean": answered, no plan
        print(f"{'answer' if reply.kind == 'answer' else reply.kind}: {reply.sentence}")
        return 0 if reply.kind == "answer" else 1
    except PlanningError as exc:
        print(f"refused: {exc}")
        return 1
    if args.json:
        print(json.dumps({"text": text, "scenario": plan.scenario, "steps": [str(p) for p in plan.primitives],
                          "slots": dict(plan.slots)}))
    else:
        print(f"plan ({plan.scenario or planner.name}): {plan}")
        for key, value in plan.slots.items():
            print(f"  {key}: {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
