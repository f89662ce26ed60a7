"""A lean replacement for robosuite 1.4's ``env.step`` that produces the same physics.

Stock ``env.step`` runs, for each of its 25 physics substeps (20 Hz control, 2 ms timestep):
``sim.forward()``; the robot's ``control()`` (OSC_POSE: ``controller.update()`` runs *another*
``sim.forward()``, reads the state through name lookups, recomputes the torques); ``sim.step()``;
and ``observable.update()`` for every observable. That is three full physics passes and a few
hundred Python calls per substep, for about 0.07 ms of useful ``mj_step``.

:class:`FastStepper` keeps every number the stock path computes and drops the rest:

* **one physics pass per substep**: ``mj_step1`` (position and velocity stages) gives the
  controller the same kinematics, Jacobians, mass matrix and bias forces that ``mj_forward``
  gives, then ``mj_step2`` (actuation, acceleration, constraints, integration) finishes the step.
  For the Euler and implicit integrators MuJoCo documents step1 + step2 as equivalent to
  ``mj_step``, and ``mj_forward`` changes no state (the solver's warm start is only written by the
  integrator), so the two extra forwards of the stock loop change nothing;
* **the same controller arithmetic, compiled**: the OSC torques are recomputed on every substep
  from the current state exactly as ``OperationalSpaceController.run_controller`` does (the same
  numba kernels ``opspace_matrices`` and ``orientation_error``, the same expressions in the same
  order). The substeps run in :mod:`services.env_worker.fast_step_kernel`, a numba loop that calls
  MuJoCo's C functions directly with the GIL released (physics and controller of several slot
  threads overlap); without numba, or for a gripper the kernel does not know, :meth:`_control`
  does the same in Python with cached index arrays and buffer views. The goal is still set once
  per control step by the controller's own ``set_goal``;
* **observables sampled when robosuite would sample them**: robosuite samples an observable on
  the substep where its timer says so (with the default 20 Hz sampling that is one substep per
  control step, which one depends on the timer's phase). The stepper replays the timer arithmetic
  on one scalar and calls the observables only on that substep, so the returned observation
  (images included) is the one ``env.step`` returns;
* **contact checks without per-contact Python**: ``check_contact`` (behind rewards, success
  predicates and grasp checks) is replaced on the instance by a vectorized version with the same
  truth table.

Result (tests/unit/test_fast_step.py): qpos, qvel, observations and rewards identical to stock
``env.step`` bit for bit over 200 random actions on LIBERO-Goal and Lift. Anything the stepper
does not reproduce exactly (another controller type, an interpolator, several robots, a viewer,
an environment that overrides ``_pre_action``) makes :func:`make_stepper` fall back to the stock
path and say why (``Stepper.reason``).

Not reproduced: robosuite's per-policy-step diagnostic ring buffers on the robot
(``recent_qpos``, ``recent_ee_forcetorques``, ...), which nothing in robosuite, LIBERO or the
families reads except ``robot.js_energy``; and the ``done`` of LIBERO's ``step`` override
(``_check_success()``): the returned ``done`` is robosuite's horizon flag, and the families decide
success themselves. Measurements and the design: docs/simulation.md.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any, Protocol

import mujoco
import numpy as np

log = logging.getLogger(__name__)

StepResult = tuple[dict[str, Any], float, bool, dict[str, Any]]


class Stepper(Protocol):
    """What a family calls instead of ``env.step``; returns what ``env.step`` returns."""

    fast: bool
    requested: bool
    reason: str

    def step(self, action: np.ndarray) -> StepResult: ...


class StockStepper:
    """The stock path: ``env.step`` itself."""

    fast = False
    requested = False

    def __init__(self, env: Any, reason: str = "fast_step disabled") -> None:
        self.env = env
        self.reason = reason

    def step(self, action: np.ndarray) -> StepResult:
        return self.env.step(action)


class UnsupportedEnv(ValueError):
    """The environment uses something the fast path does not reproduce exactly."""


def make_stepper(env: Any, fast: bool = True) -> StockStepper | FastStepper:
    """The stepper of ``env``, built once and kept on the env (envs are pooled and reused)."""
    cached = getattr(env, "_zetta_stepper", None)
    if cached is not None and cached.requested == fast and cached.env is env:
        return cached
    stepper: StockStepper | FastStepper
    if fast:
        try:
            stepper = FastStepper(env)
        except UnsupportedEnv as exc:
            log.warning("fast step unavailable for %s, using env.step: %s", type(env).__name__, exc)
            stepper = StockStepper(env, reason=str(exc))
    else:
        stepper = StockStepper(env)
    stepper.requested = fast
    env._zetta_stepper = stepper
    return stepper


def warm_up() -> float:
    """Compile (or load from numba's disk cache) the substep kernel; returns the seconds it took.

    The env worker runs this on a background thread at start-up so the first step of the first
    slot does not pay for it (about 1 s from the cache, 10-20 s for a first compile).
    """
    import time

    start = time.perf_counter()
    try:
        import robosuite  # noqa: F401 - the kernel module expects robosuite to be imported first

        from services.env_worker.fast_step_kernel import compile_kernel

        compile_kernel()
    except Exception as exc:  # noqa: BLE001 - the Python substeps are exact too, only slower
        log.warning("fast step kernel unavailable (%s); fast_step uses Python substeps", exc)
    return time.perf_counter() - start


def _allowed_overrides() -> dict[str, tuple[Any, ...]]:
    """Env methods the stepper replaces, and the implementations it reproduces."""
    from robosuite.environments.base import MujocoEnv
    from robosuite.environments.robot_env import RobotEnv

    pre = [RobotEnv._pre_action]
    step = [MujocoEnv.step]
    try:  # LIBERO overrides both with thin wrappers around the robosuite ones
        from libero.libero.envs.bddl_base_domain import BDDLBaseDomain

        pre.append(BDDLBaseDomain._pre_action)
        step.append(BDDLBaseDomain.step)
    except ImportError:  # pragma: no cover - LIBERO is installed with the project
        pass
    return {"_pre_action": tuple(pre), "step": tuple(step)}


class FastStepper:
    """Steps one robosuite (or LIBERO) environment like ``env.step``, minus the overhead.

    Build it once per env; it re-reads everything that can change between steps (controller goal
    and gains, gripper command, observable timers) from the env's own objects, so resets, slot
    reuse and stock ``env.step`` calls can be interleaved with it.
    """

    fast = True
    requested = True
    reason = ""

    def __init__(self, env: Any, compiled: bool = True) -> None:
        from robosuite.robots.single_arm import SingleArm
        from robosuite.utils.control_utils import nullspace_torques, opspace_matrices, orientation_error

        self.env = env
        cls = type(env)
        for name, allowed in _allowed_overrides().items():
            if getattr(cls, name, None) not in allowed:
                raise UnsupportedEnv(f"{cls.__name__} overrides {name}")
        if len(env.robots) != 1 or not isinstance(env.robots[0], SingleArm):
            raise UnsupportedEnv("only single-arm, single-robot environments")
        robot = env.robots[0]
        self._check_controller(robot.controller)
        if getattr(env, "viewer", None) is not None or getattr(env, "viewer_get_obs", False):
            raise UnsupportedEnv("an on-screen viewer is attached")
        substeps = env.control_timestep / env.model_timestep
        if not math.isclose(substeps, round(substeps)):
            raise UnsupportedEnv(f"control timestep is not a whole number of substeps ({substeps})")
        self._opspace = opspace_matrices
        self._ori_error = orientation_error
        self._nullspace = nullspace_torques
        self._robot = robot
        self._ctrl = robot.controller
        self._gripper = robot.gripper if robot.has_gripper else None
        self._sim: Any = None
        self._contact_masks: dict[tuple[Any, ...], np.ndarray] = {}
        self._contact_geoms_of: dict[int, tuple[Any, tuple[str, ...]]] = {}
        self._kernel = self._load_kernel() if compiled else None
        if compiled and self._kernel is None:
            self.reason = "compiled kernel unavailable; Python substeps"
        self._bind()
        env.check_contact = self._check_contact  # same truth table, no per-contact Python

    def _load_kernel(self) -> Any:
        """The numba substep loop, if this robot's gripper is one it reproduces."""
        from robosuite.models.grippers.panda_gripper import PandaGripper

        gripper = self._gripper
        if gripper is not None and not (
            type(gripper).format_action is PandaGripper.format_action
            and gripper.dof == 1
            and len(gripper.actuators) == 2
        ):
            return None
        try:
            from services.env_worker.fast_step_kernel import compile_kernel

            return compile_kernel()
        except Exception as exc:  # noqa: BLE001 - numba or libmujoco missing: the Python substeps are still exact
            log.warning("fast step kernel unavailable (%s); using Python substeps", exc)
            return None

    @staticmethod
    def _check_controller(ctrl: Any) -> None:
        from robosuite.controllers.osc import OperationalSpaceController

        if type(ctrl) is not OperationalSpaceController:
            raise UnsupportedEnv(f"controller {type(ctrl).__name__} (only OSC is reproduced)")
        if ctrl.interpolator_pos is not None or ctrl.interpolator_ori is not None:
            raise UnsupportedEnv("OSC with an interpolator")

    # -- caches -------------------------------------------------------------------------------

    def _bind(self) -> None:
        """Cache ids, index arrays and buffer views of the env's current simulation."""
        env, robot, ctrl = self.env, self._robot, self._ctrl
        sim = env.sim
        m, d = sim.model._model, sim.data._data
        self._sim, self._m, self._d = sim, m, d
        self._step_split = m.opt.integrator != mujoco.mjtIntegrator.mjINT_RK4
        self._sid = sim.model.site_name2id(ctrl.eef_name)
        self._qpos_index = np.asarray(ctrl.qpos_index, dtype=np.intp)
        self._qvel_index = np.asarray(ctrl.qvel_index, dtype=np.intp)
        self._arm_ctrl = np.asarray(robot._ref_joint_actuator_indexes, dtype=np.intp)
        low, high = robot.torque_limits
        self._torque_low, self._torque_high = np.array(low), np.array(high)
        self._control_dim = ctrl.control_dim
        if self._gripper is not None:
            ids = [sim.model.actuator_name2id(a) for a in self._gripper.actuators]
            ctrl_range = sim.model.actuator_ctrlrange[ids]
            self._grip_ctrl = np.asarray(ids, dtype=np.intp)
            self._grip_bias = 0.5 * (ctrl_range[:, 1] + ctrl_range[:, 0])
            self._grip_weight = 0.5 * (ctrl_range[:, 1] - ctrl_range[:, 0])
        else:
            self._grip_ctrl = np.zeros(0, dtype=np.intp)
            self._grip_bias = self._grip_weight = np.zeros(0)
        self._m_ptr, self._d_ptr = m._address, d._address
        # Views into MjData's buffers; they stay valid for the life of the MjData.
        self._qpos, self._qvel, self._ctrl_buf = d.qpos, d.qvel, d.ctrl
        self._site_xpos, self._site_xmat, self._qfrc_bias = d.site_xpos, d.site_xmat, d.qfrc_bias
        self._jacp = np.zeros((3, m.nv))
        self._jacr = np.zeros((3, m.nv))
        self._full_mass = np.zeros((m.nv, m.nv))
        self._substeps = int(round(env.control_timestep / env.model_timestep))
        self._contact_masks.clear()
        self._contact_geoms_of.clear()
        self._geom_names = [sim.model.geom_id2name(g) for g in range(m.ngeom)]

    # -- the step -------------------------------------------------------------------------------

    def step(self, action: np.ndarray) -> StepResult:
        """What ``env.step(action)`` does, with the same results."""
        env = self.env
        if env.done:
            raise ValueError("executing action in terminated episode")
        sim = env.sim
        if self._robot.controller is not self._ctrl:  # robot.reset() builds a new controller
            self._check_controller(self._robot.controller)
            self._ctrl = self._robot.controller
            self._bind()
        elif sim is not self._sim or sim.model._model is not self._m or sim.data._data is not self._d:
            self._bind()
        if len(action) != env.action_dim:
            raise AssertionError(
                f"environment got invalid action dimension -- expected {env.action_dim}, got {len(action)}"
            )
        env.timestep += 1
        robot_action = action[: self._robot.action_dim]
        arm_action = robot_action[: self._control_dim]
        grip_action = robot_action[self._control_dim :]
        timer = _ObservableTimer.of(env)
        if self._kernel is not None:
            self._compiled_substeps(arm_action, grip_action, timer)
        else:
            for i in range(self._substeps):
                self._stage1()
                self._control(arm_action, grip_action, policy_step=i == 0)
                self._stage2()
                self._observe(timer)
        if timer is not None:
            timer.store(env)
        env.cur_time += env.control_timestep
        reward, done, info = env._post_action(action)
        return env._get_observations(), reward, done, info

    def _stage1(self) -> None:
        """Physics up to the controller: what the stock loop's ``sim.forward()`` provides."""
        if self._step_split:
            mujoco.mj_step1(self._m, self._d)
        else:
            mujoco.mj_forward(self._m, self._d)

    def _stage2(self) -> None:
        """The rest of the physics substep, with the new controls."""
        if self._step_split:
            mujoco.mj_step2(self._m, self._d)
        else:
            mujoco.mj_step(self._m, self._d)

    def _observe(self, timer: _ObservableTimer | None) -> None:
        """The observable updates of one substep."""
        if timer is None:
            self.env._update_observables()
        else:
            timer.advance(self.env)

    def _compiled_substeps(
        self, arm_action: np.ndarray, grip_action: np.ndarray, timer: _ObservableTimer | None
    ) -> None:
        """The substeps of one control step through the GIL-free kernel, split where observables sample."""
        ctrl, n = self._ctrl, self._substeps
        self._stage1()
        if not ctrl.new_update:
            # First step after a reset: substep 0 uses the controller's stored state (see _control).
            self._control(arm_action, grip_action, policy_step=True)
            self._stage2()
            self._observe(timer)
            done, skip_stage1 = 1, False
        else:
            ctrl.ee_pos = np.array(self._site_xpos[self._sid])
            ctrl.ee_ori_mat = np.array(self._site_xmat[self._sid].reshape([3, 3]))
            ctrl.new_update = False  # set_goal reads only the pose, which is now current
            ctrl.set_goal(arm_action)
            done, skip_stage1 = 0, True
        gripper = self._gripper
        if gripper is not None:
            grip_sign = float(np.sign(grip_action)[0])
            grip_current = np.array(gripper.current_action, dtype=np.float64)
            grip_speed = float(gripper.speed)
        else:
            grip_sign, grip_current, grip_speed = 0.0, np.zeros(0), 0.0
        goal_pos = np.ascontiguousarray(ctrl.goal_pos, dtype=np.float64)
        goal_ori = np.ascontiguousarray(ctrl.goal_ori, dtype=np.float64)
        kp = np.ascontiguousarray(ctrl.kp, dtype=np.float64)
        kd = np.ascontiguousarray(ctrl.kd, dtype=np.float64)
        initial_joint = np.ascontiguousarray(ctrl.initial_joint, dtype=np.float64)
        out = None
        while done < n:
            left = n - done
            quiet = 0 if timer is None else timer.quiet_substeps(left)
            seg = min(quiet + 1, left)
            out = self._kernel(
                self._m_ptr, self._d_ptr, seg, self._step_split, skip_stage1,
                self._sid, self._qpos_index, self._qvel_index, self._arm_ctrl,
                self._grip_ctrl, self._grip_bias, self._grip_weight, grip_sign, grip_current, grip_speed,
                goal_pos, goal_ori, kp, kd, bool(ctrl.uncoupling), initial_joint, self._torque_low, self._torque_high,
                self._qpos, self._qvel, self._ctrl_buf, self._site_xpos, self._site_xmat, self._qfrc_bias,
                self._jacp, self._jacr, self._full_mass,
            )
            skip_stage1 = False
            done += seg
            if timer is None:
                self._sync(out, grip_current)
                self.env._update_observables()
            else:
                timer.skip(min(quiet, seg))
                if quiet < left:
                    self._sync(out, grip_current)
                    timer.advance(self.env)
        if out is not None:
            self._sync(out, grip_current)

    def _sync(self, out: tuple[np.ndarray, ...], grip_current: np.ndarray) -> None:
        """Leave the controller, robot and gripper as the stock loop leaves them after a substep."""
        ctrl = self._ctrl
        (ctrl.ee_pos, ctrl.ee_ori_mat, ctrl.ee_pos_vel, ctrl.ee_ori_vel, ctrl.joint_pos, ctrl.joint_vel,
         ctrl.J_pos, ctrl.J_ori, ctrl.J_full, ctrl.mass_matrix, torques) = (np.array(a) for a in out)
        ctrl.torques = torques
        ctrl.new_update = True
        self._robot.torques = torques
        if self._gripper is not None:
            self._gripper.current_action = grip_current.copy()

    def _control(self, arm_action: np.ndarray, grip_action: np.ndarray, policy_step: bool) -> None:
        """SingleArm.control -> OperationalSpaceController.{set_goal, run_controller}, inlined."""
        ctrl, d, sid = self._ctrl, self._d, self._sid
        if policy_step and not ctrl.new_update:
            # Right after a reset the controller holds the state it read then (update(force=True)),
            # and robosuite's first substep uses that state rather than the current one.
            self._run_controller(
                arm_action, grip_action, ctrl.ee_pos, ctrl.ee_ori_mat, ctrl.ee_pos_vel, ctrl.ee_ori_vel,
                ctrl.joint_pos, ctrl.joint_vel, ctrl.J_pos, ctrl.J_ori, ctrl.J_full, ctrl.mass_matrix, set_goal=True,
            )
            return
        # Controller.update(): the state the controller reads.
        ee_pos = np.array(self._site_xpos[sid])
        ee_ori_mat = np.array(self._site_xmat[sid].reshape([3, 3]))
        jacp, jacr = self._jacp, self._jacr
        mujoco.mj_jacSite(self._m, d, jacp, jacr, sid)
        ee_pos_vel = np.dot(jacp, self._qvel)
        ee_ori_vel = np.dot(jacr, self._qvel)
        joint_pos = self._qpos[self._qpos_index]
        joint_vel = self._qvel[self._qvel_index]
        J_pos = jacp[:, self._qvel_index]
        J_ori = jacr[:, self._qvel_index]
        J_full = np.array(np.vstack([J_pos, J_ori]))
        mujoco.mj_fullM(self._m, d, self._full_mass)
        mass_matrix = self._full_mass[self._qvel_index, :][:, self._qvel_index]  # robosuite's layout (F order)
        self._run_controller(
            arm_action, grip_action, ee_pos, ee_ori_mat, ee_pos_vel, ee_ori_vel, joint_pos, joint_vel,
            J_pos, J_ori, J_full, mass_matrix, set_goal=policy_step,
        )

    def _run_controller(
        self, arm_action: np.ndarray, grip_action: np.ndarray, ee_pos: np.ndarray, ee_ori_mat: np.ndarray,
        ee_pos_vel: np.ndarray, ee_ori_vel: np.ndarray, joint_pos: np.ndarray, joint_vel: np.ndarray,
        J_pos: np.ndarray, J_ori: np.ndarray, J_full: np.ndarray, mass_matrix: np.ndarray, set_goal: bool,
    ) -> None:
        ctrl = self._ctrl
        # Controller.update() stores what it read; set_goal and any later reader see it.
        ctrl.ee_pos, ctrl.ee_ori_mat, ctrl.ee_pos_vel, ctrl.ee_ori_vel = ee_pos, ee_ori_mat, ee_pos_vel, ee_ori_vel
        ctrl.joint_pos, ctrl.joint_vel, ctrl.J_pos, ctrl.J_ori, ctrl.J_full = joint_pos, joint_vel, J_pos, J_ori, J_full
        ctrl.mass_matrix = mass_matrix
        if set_goal:
            ctrl.new_update = False  # set_goal's update() would only read the same values again
            ctrl.set_goal(arm_action)
        # OperationalSpaceController.run_controller (no interpolators).
        kp, kd = ctrl.kp, ctrl.kd
        desired_pos = np.array(ctrl.goal_pos)
        ori_error = self._ori_error(np.array(ctrl.goal_ori), ee_ori_mat)
        position_error = desired_pos - ee_pos
        desired_force = np.multiply(np.array(position_error), np.array(kp[0:3])) + np.multiply(-ee_pos_vel, kd[0:3])
        desired_torque = np.multiply(np.array(ori_error), np.array(kp[3:6])) + np.multiply(-ee_ori_vel, kd[3:6])
        lambda_full, lambda_pos, lambda_ori, nullspace_matrix = self._opspace(mass_matrix, J_full, J_pos, J_ori)
        if ctrl.uncoupling:
            wrench = np.concatenate([np.dot(lambda_pos, desired_force), np.dot(lambda_ori, desired_torque)])
        else:
            wrench = np.dot(lambda_full, np.concatenate([desired_force, desired_torque]))
        torques = np.dot(J_full.T, wrench) + self._qfrc_bias[self._qvel_index]
        torques += self._nullspace(mass_matrix, nullspace_matrix, ctrl.initial_joint, joint_pos, joint_vel)
        # SingleArm.control: clip, gripper, write the actuators.
        torques = np.clip(torques, self._torque_low, self._torque_high)
        if self._gripper is not None:
            command = self._gripper.format_action(grip_action)
            self._ctrl_buf[self._grip_ctrl] = self._grip_bias + self._grip_weight * command
        self._ctrl_buf[self._arm_ctrl] = torques
        # Leave the controller and robot as run_controller / control would.
        ctrl.torques = torques
        ctrl.new_update = True
        self._robot.torques = torques

    # -- contacts -------------------------------------------------------------------------------

    def _check_contact(self, geoms_1: Any, geoms_2: Any = None) -> bool:
        """MujocoEnv.check_contact with the contact loop in numpy (same result for every input)."""
        from robosuite.models.base import MujocoModel

        if type(geoms_1) is str:
            geoms_1 = [geoms_1]
        elif isinstance(geoms_1, MujocoModel):
            geoms_1 = self._model_geoms(geoms_1)
        if type(geoms_2) is str:
            geoms_2 = [geoms_2]
        elif isinstance(geoms_2, MujocoModel):
            geoms_2 = self._model_geoms(geoms_2)
        d = self.env.sim.data._data
        if d is not self._d:
            self._bind()
        ncon = d.ncon
        if ncon == 0:
            return False
        in1 = self._mask(geoms_1)
        g1, g2 = d.contact.geom1[:ncon], d.contact.geom2[:ncon]
        if geoms_2 is None:
            return bool(np.any(in1[g1] | in1[g2]))
        in2 = self._mask(geoms_2)
        return bool(np.any((in1[g1] & in2[g2]) | (in2[g1] & in1[g2])))

    def _model_geoms(self, model: Any) -> tuple[str, ...]:
        """A robosuite model's contact geom names; its ``contact_geoms`` property rebuilds the
        prefixed list on every access, and the names never change after the model is built."""
        found = self._contact_geoms_of.get(id(model))
        if found is None or found[0] is not model:
            found = (model, tuple(model.contact_geoms))
            self._contact_geoms_of[id(model)] = found
        return found[1]

    def _mask(self, geoms: Sequence[Any]) -> np.ndarray:
        try:
            key = tuple(geoms)
            mask = self._contact_masks.get(key)
        except TypeError:  # unhashable entries: compute without caching
            key, mask = None, None
        if mask is None:
            mask = np.array([name in geoms for name in self._geom_names], dtype=bool)
            if key is not None and len(self._contact_masks) < 4096:
                self._contact_masks[key] = mask
        return mask


class _ObservableTimer:
    """robosuite's per-observable sampling timer, replayed once for observables that share it.

    ``Observable.update`` adds the model timestep to a timer each substep, samples when the timer
    is inside the sampling window and has not sampled yet, and wraps the timer once it passes the
    sampling period. When every enabled observable has the same timer state and period and no
    delay (robosuite's defaults), the arithmetic is the same for all of them: run it on one scalar
    and call the observables' own ``update`` only on the substeps where it samples or wraps.
    """

    __slots__ = ("observables", "t", "sampled", "delay", "period", "dt")

    @classmethod
    def of(cls, env: Any) -> _ObservableTimer | None:
        """The shared timer of ``env``'s enabled observables, or None if they do not share one."""
        from robosuite.utils.observables import NO_DELAY, Observable

        enabled = [o for o in env._observables.values() if o._enabled]
        if not enabled or any(type(o) is not Observable for o in enabled):
            return None
        first = enabled[0]
        state = (first._time_since_last_sample, first._sampled, first._sampling_timestep, first._current_delay)
        for o in enabled:
            if (o._time_since_last_sample, o._sampled, o._sampling_timestep, o._current_delay) != state:
                return None
            if o._delayer is not NO_DELAY:
                return None
        timer = cls()
        timer.observables = enabled
        timer.t, timer.sampled, timer.period, timer.delay = state[0], state[1], state[2], state[3]
        timer.dt = env.model_timestep
        return timer

    def advance(self, env: Any) -> None:
        """One substep of every enabled observable's ``update``."""
        t = self.t + self.dt
        if not self._fires(t):
            self.t = t
            return
        # Let the observables do this substep themselves, from the shared state, in env order.
        for o in self.observables:
            o._time_since_last_sample, o._sampled = self.t, self.sampled
        cache = env._obs_cache
        for o in self.observables:
            o.update(timestep=self.dt, obs_cache=cache, force=False)
        first = self.observables[0]
        self.t, self.sampled, self.delay = first._time_since_last_sample, first._sampled, first._current_delay

    def _fires(self, t: float) -> bool:
        return (not self.sampled and self.period - self.delay >= t) or t >= self.period

    def quiet_substeps(self, limit: int) -> int:
        """How many of the next ``limit`` substeps pass before one where the observables act."""
        t = self.t
        for k in range(limit):
            t = t + self.dt
            if self._fires(t):
                return k
        return limit

    def skip(self, count: int) -> None:
        """Advance the timer over ``count`` substeps where nothing fires."""
        for _ in range(count):
            self.t = self.t + self.dt

    def store(self, env: Any) -> None:
        """Write the timer back into every observable, as if each had been updated every substep."""
        for o in self.observables:
            o._time_since_last_sample, o._sampled, o._current_delay = self.t, self.sampled, self.delay
