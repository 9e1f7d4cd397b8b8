"""``+rescue`` (``curlnav.nav.recovery.rescue``): a policy that stalls in front of a trap is taken round
it by ``dwa`` on a plan over its own scans, and hands back; a policy that makes progress is never
overridden."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import GoalSeeker, u_trap_world
from conftest import run_pairs as run

from curlnav.evaluation.protocol import evaluation_config
from curlnav.layout import ObservationLayout
from curlnav.nav import make_agent, parse_agent
from curlnav.nav.controllers.local import DynamicWindowPlanner
from curlnav.nav.global_planners.scan_map import ScanMapPlanAgent
from curlnav.nav.recovery.rescue import RescueConfig, RescuedPolicy
from curlnav.nav.safety.shield import ShieldedPolicy
from curlnav.sim import NamoEnv


class CautiousSeeker(GoalSeeker):
    """A goal seeker that stops a metre short of whatever lies straight ahead: in front of the
    bottom of a U it waits for ever, with room to turn."""

    def __init__(self, cfg) -> None:
        super().__init__()
        self.layout = ObservationLayout.from_env_config(cfg)
        self.ahead = np.abs(np.linspace(-cfg.lidar_fov / 2, cfg.lidar_fov / 2, cfg.lidar_beams)) < 0.35

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        action = super().__call__(observation)
        ranges, _, _ = self.layout.newest_frame(observation)
        if ranges[self.ahead].min() < 1.0:
            action[0] = 0.0
        return action


def test_a_policy_stalled_in_a_u_trap_is_rescued_round_it_and_drives_the_rest_itself():
    """A goal seeker that keeps a metre from what lies ahead waits in front of the bottom of a U
    and times out; with the rescue, dwa on a plan over its scans takes it round the U without a
    contact, and the policy drives the steps before and after."""
    cfg = evaluation_config()
    world = u_trap_world()
    stuck = run(CautiousSeeker(cfg), world, cfg)
    assert stuck.success_rate == 0.0 and stuck.collisions_per_episode == 0, "the trap holds it without the rescue"
    seeker = CautiousSeeker(cfg)
    rescued = RescuedPolicy(seeker, cfg)
    result = run(rescued, world, cfg)
    assert result.success_rate == 1.0 and result.collisions_per_episode == 0
    assert rescued.rescues >= 1 and rescued.rescue_steps > 0
    assert seeker.calls > rescued.rescue_steps, "the policy drove most of the episode"


def test_a_policy_that_keeps_coming_nearer_is_never_overridden():
    cfg = evaluation_config()
    world = u_trap_world()
    seeker = GoalSeeker()
    rescued = RescuedPolicy(seeker, cfg, RescueConfig(stall_steps=5))
    env = NamoEnv(world, cfg)
    try:
        obs, info = env.reset(seed=0, options={"pair": 0})
        rescued.reset(world, world.pairs[0])
        for _ in range(25):  # 5 m toward the U's bottom at 1 m/s: 0.5 m nearer every 3 steps
            action = rescued.act(obs, info)
            assert np.array_equal(action, GoalSeeker()(obs)), "the policy's own command"
            obs, _, terminated, truncated, info = env.step(action)
            assert not (terminated or truncated)
    finally:
        env.close()
    assert rescued.rescues == 0 and rescued.rescue_steps == 0


def test_rescue_stacks_between_the_plan_and_the_shield_and_map_less_planners_take_suffixes():
    cfg = evaluation_config()
    label, agent = make_agent("my-policy+scan-plan+rescue+shield", cfg, lambda spec: GoalSeeker())
    assert label == "my-policy+scan-plan+rescue+shield"
    assert isinstance(agent, ShieldedPolicy) and isinstance(agent.policy, RescuedPolicy)
    assert isinstance(agent.policy.policy, ScanMapPlanAgent)
    label, agent = make_agent("dwa+scan-plan", cfg, lambda spec: pytest.fail("dwa is no policy to load"))
    assert isinstance(agent, ScanMapPlanAgent) and isinstance(agent.policy, DynamicWindowPlanner)
    for spec in ("p+rescue+scan-plan", "p+shield+rescue", "p+rescue+rescue"):
        with pytest.raises(ValueError, match="suffixes stack|named 2 times"):
            make_agent(spec, cfg, lambda s: GoalSeeker())
    for spec in ("dwa+global-plan", "dwa+global-plan+rescue"):
        with pytest.raises(ValueError, match="global plan is for policies"):
            make_agent(spec, cfg, lambda s: GoalSeeker())
    label, agent = make_agent("my-policy+global-plan+rescue", cfg, lambda spec: GoalSeeker())
    assert isinstance(agent, RescuedPolicy), "built without a world: the plan is made at reset"
    with pytest.raises(ValueError, match="true map"):
        make_agent("oracle+shield", cfg, lambda s: GoalSeeker())


@pytest.mark.parametrize("bad", [{"stall_steps": 0}, {"max_steps": 1.5}, {"progress_m": -1.0},
                                 {"progress_m": float("nan")}])
def test_bad_rescue_settings_are_refused_by_name(bad):
    with pytest.raises(ValueError, match=f"rescue: {next(iter(bad))}"):
        RescueConfig(**bad)


def test_the_rescues_dwa_backs_away_from_a_wall_too_near_to_turn_at_where_the_robot_can_reverse():
    """A wall 5 cm ahead of the bumper (inside DWA's 10 cm margin): forward-only DWA can only stop;
    a DWA that may back up (``reverse=True``, as the rescue's where ``RescueConfig.reverse`` asks),
    on a robot with a reverse gear, backs away."""
    import dataclasses

    from curlnav.nav.controllers.local import DwaConfig

    reversing = evaluation_config()  # the Husky backs up at 0.5 m/s
    cfg = reversing.replace(robot=dataclasses.replace(reversing.robot, max_reverse_speed=0.0))
    front = cfg.robot.base_length / 2 + 0.05
    wall = np.stack([np.full(41, front), np.linspace(-1.0, 1.0, 41)], axis=1)  # m, robot frame
    assert DynamicWindowPlanner(reversing).choose(wall, 5.0, 0.0) == (0.0, 0.0), "the baseline stops"
    v, _ = DynamicWindowPlanner(reversing, DwaConfig(reverse=True)).choose(wall, 5.0, 0.0)
    assert v < 0
    v, _ = DynamicWindowPlanner(cfg, DwaConfig(reverse=True)).choose(wall, 5.0, 0.0)
    assert v == 0.0, "a forward-only robot never backs up"


def test_an_artefact_named_alone_drives_with_the_helpers_its_metadata_ships_and_bare_without(tmp_path):
    """``metadata.json`` ``deploy: "+rescue+shield"``: ``curlnav eval ARTEFACT`` drives it behind
    both (label: the path as given), ``ARTEFACT+bare`` is the network alone, explicit suffixes win,
    and a malformed stack is refused in one line."""
    import json

    cfg = evaluation_config()
    artefact = tmp_path / "policy"
    artefact.mkdir()
    (artefact / "metadata.json").write_text(json.dumps({"deploy": "+rescue+shield"}))
    load = lambda spec: GoalSeeker()  # noqa: E731
    label, agent = make_agent(str(artefact), cfg, load)
    assert label == str(artefact)
    assert isinstance(agent, ShieldedPolicy) and isinstance(agent.policy, RescuedPolicy)
    label, agent = make_agent(f"{artefact}+bare", cfg, load)
    assert isinstance(agent, GoalSeeker) and label == f"{artefact}+bare"
    _, agent = make_agent(f"{artefact}+shield", cfg, load)
    assert isinstance(agent, ShieldedPolicy) and isinstance(agent.policy, GoalSeeker), "the suffixes given win"
    with pytest.raises(ValueError, match=r"\+bare is the network alone"):
        make_agent(f"{artefact}+shield+bare", cfg, load)
    (artefact / "metadata.json").write_text(json.dumps({"deploy": "+shield+rescue"}))
    with pytest.raises(ValueError, match="deploy must be suffixes"):
        make_agent(str(artefact), cfg, load)


def test_the_global_plan_flag_keeps_an_artefacts_shipped_helpers_and_says_so_in_the_label(tmp_path):
    import json

    from curlnav.nav.global_planners.global_plan import GlobalPlanAgent

    cfg = evaluation_config()
    artefact = tmp_path / "policy"
    artefact.mkdir()
    (artefact / "metadata.json").write_text(json.dumps({"deploy": "+rescue+shield"}))
    load = lambda spec: GoalSeeker()  # noqa: E731
    label, agent = make_agent(str(artefact), cfg, load, global_plan=True)
    assert label == f"{artefact}+global-plan"
    assert isinstance(agent.policy, RescuedPolicy) and isinstance(agent.policy.policy, GlobalPlanAgent)
    label, agent = make_agent(f"{artefact}+bare", cfg, load, global_plan=True)
    assert label == f"{artefact}+bare+global-plan" and isinstance(agent, GlobalPlanAgent)
    _, agent = make_agent(str(artefact / "metadata.json"), cfg, load)
    assert isinstance(agent, ShieldedPolicy), "the artefact named by its metadata file ships the same"


def test_an_artefacts_rescue_settings_reach_its_rescue_wherever_it_drives_and_bad_ones_are_refused(tmp_path,
                                                                                                 monkeypatch):
    """``metadata.json`` ``deploy_settings.rescue``: the rescue it drives behind takes over after the
    artefact's own stall count (named alone, with the suffix, and in the ROS 2 node); other fields
    keep their defaults; a policy without settings has the defaults; a wrong key or value is
    refused in one line naming the file."""
    import json

    from curlnav.nav import deploy_notice, rescue_settings
    from curlnav.ros2.commands import deployed
    from curlnav.ros2.node import ScanLayout

    cfg = evaluation_config()
    artefact = tmp_path / "policy"
    artefact.mkdir()
    meta = artefact / "metadata.json"
    meta.write_text(json.dumps({"deploy": "+rescue+shield", "deploy_settings": {"rescue": {"stall_steps": 10}}}))
    load = lambda spec: GoalSeeker()  # noqa: E731
    for spec in (str(artefact), f"{artefact}+rescue"):
        _, agent = make_agent(spec, cfg, load)
        rescue = agent.policy if isinstance(agent, ShieldedPolicy) else agent
        assert isinstance(rescue, RescuedPolicy), spec
        assert rescue.config == RescueConfig(stall_steps=10), spec
    node_agent = deployed(lambda obs: np.zeros(3), ScanLayout(), "husky", parse_agent(f"{artefact}+rescue"))
    assert isinstance(node_agent, RescuedPolicy) and node_agent.config.stall_steps == 10
    assert rescue_settings(str(meta)) == RescueConfig(stall_steps=10), "named by its metadata file"
    assert "its rescue: stall_steps 10" in deploy_notice(str(artefact), "+bare")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "dwa").mkdir()
    (tmp_path / "dwa" / "metadata.json").write_text(meta.read_text())
    assert make_agent("dwa+rescue", cfg, load)[1].config == RescueConfig(), "a planner's name is no artefact"
    meta.write_text("{not json")
    assert rescue_settings(str(artefact)) is None, "a broken file is the policy loader's to report"
    meta.write_text(json.dumps({"deploy": "+rescue+shield"}))
    assert rescue_settings(str(artefact)) is None and make_agent(str(artefact), cfg, load)[1].policy.config == RescueConfig()
    for settings, message in (({"rescue": {"stall_step": 10}},
                               "deploy_settings.rescue: no setting 'stall_step'; settings: max_steps"),
                              ({"shield": {}}, "at most the key 'rescue'"),
                              ({"rescue": {"stall_steps": 0}}, "stall_steps must be a whole number")):
        meta.write_text(json.dumps({"deploy": "+rescue+shield", "deploy_settings": settings}))
        with pytest.raises(ValueError, match=message) as err:
            make_agent(str(artefact), cfg, load)
        assert str(meta) in str(err.value)


def test_behind_a_global_plan_the_rescue_follows_the_plan():
    """``POLICY+global-plan+rescue``: the fallback is the plan's path tracker (regulated pure
    pursuit of the very A* path the policy's waypoints come from, ``GlobalPlanAgent.track``), not a
    plan on its own scans to the final goal. A policy that never moves, behind a global plan round
    a U of walls, is driven round it by the rescue alone, without a contact, along the plan; and
    ``make_agent`` builds that fallback for the flag and the suffix."""
    from curlnav.nav.global_planners.global_plan import GlobalPlanAgent
    from curlnav.nav.recovery.rescue import PlanTracker, global_plan_fallback

    cfg = evaluation_config()
    world = u_trap_world()
    still = lambda observation: np.zeros(3, np.float32)  # noqa: E731
    planned = GlobalPlanAgent(still, cfg)
    rescued = RescuedPolicy(planned, cfg, RescueConfig(stall_steps=2, max_steps=1000), fallback=global_plan_fallback(planned))
    result = run(rescued, world, cfg)
    assert result.success_rate == 1.0 and result.collisions_per_episode == 0
    assert rescued.rescue_steps > 20
    driven = np.array(planned.tracker.path)  # the path the rescue tracked goes round the U's arm ...
    assert (np.abs(driven[:, 1] - 5.0) > 3.0).any()
    assert planned.tracker.path is planned.plan.path, "... and is the plan the policy's waypoints come from"
    for spec, flag in (("p+global-plan+rescue+shield", False), ("p+rescue+shield", True)):
        _, agent = make_agent(spec, cfg, lambda s: GoalSeeker(), global_plan=flag)
        assert isinstance(agent.policy.fallback, PlanTracker)
        assert agent.policy.fallback.planned is agent.policy.policy, "the tracker of the plan the policy follows"
    _, agent = make_agent("p+rescue+shield", cfg, lambda s: GoalSeeker())
    assert isinstance(agent.policy.fallback, ScanMapPlanAgent), "without a global plan: dwa on its own scans"
