"""The compiled substep loop of :mod:`services.env_worker.fast_step`: OSC torques plus physics, GIL-free.

One call runs ``n`` physics substeps of a control step: ``mj_step1`` (position and velocity
stages), the OSC_POSE torques and the Panda gripper command, ``mj_step2``. MuJoCo is called
through its C symbols (``libmujoco`` shipped in the ``mujoco`` wheel, the same library the
Python bindings use) so the whole loop runs in numba's nopython mode with the GIL released:
several slot threads of one worker step their physics *and* their controllers in parallel.

The arithmetic mirrors robosuite 1.4's ``OperationalSpaceController.run_controller`` and
``nullspace_torques`` expression by expression, and calls robosuite's own numba kernels
(``opspace_matrices``, ``orientation_error``) with arrays laid out as robosuite lays them out
(the fancy-indexed Jacobians, their stack and the mass matrix are Fortran-ordered there), so numba picks the same
compiled specializations and the same BLAS/LAPACK calls. tests/unit/test_fast_step.py checks the
result bit for bit against stock ``env.step``.

Compiling takes 10-20 s on the 2-core machines the first time; numba caches the machine code on
disk (``cache=True``, next to this file or under ``NUMBA_CACHE_DIR``), and later processes load it
in about a second. :func:`compile_kernel` does either; the env worker calls it at start-up, before
it takes sessions. Import this module only after robosuite has been imported (the families do).
"""

from __future__ import annotations

import ctypes
import threading
from typing import Any

import llvmlite.binding as llvm
import numpy as np
import robosuite.macros as macros
from numba import njit, types
from robosuite.utils.control_utils import opspace_matrices, orientation_error
from services.env_worker import libmujoco


def _libmujoco() -> str:
    where = libmujoco.path()
    if where is None:
        raise ImportError("libmujoco not found next to the mujoco package")
    return where


if not macros.ENABLE_NUMBA:
    raise ImportError("robosuite runs its controller kernels without numba (macros.ENABLE_NUMBA is False)")

ctypes.CDLL(_libmujoco())  # already loaded by the bindings; make its symbols resolvable for numba
llvm.load_library_permanently(_libmujoco())

_PTR = types.intp  # mjModel*, mjData*, mjtNum*: passed as addresses (same calling convention)
mj_step1 = types.ExternalFunction("mj_step1", types.void(_PTR, _PTR))
mj_step2 = types.ExternalFunction("mj_step2", types.void(_PTR, _PTR))
mj_forward = types.ExternalFunction("mj_forward", types.void(_PTR, _PTR))
mj_step = types.ExternalFunction("mj_step", types.void(_PTR, _PTR))
mj_jac_site = types.ExternalFunction("mj_jacSite", types.void(_PTR, _PTR, _PTR, _PTR, types.intc))
mj_full_m = types.ExternalFunction("mj_fullM", types.void(_PTR, _PTR, _PTR))

_LOCK = threading.Lock()
_COMPILED = False


def compile_kernel() -> Any:
    """The jitted substep loop, compiled (or loaded from numba's on-disk cache) on first call.

    Compiling takes 10-20 s on the 2-core machines; loading the cached machine code about 1 s.
    """
    global _COMPILED
    with _LOCK:
        if not _COMPILED:
            _warm_up()
            _COMPILED = True
    return substeps


def _warm_up() -> None:
    """Call the kernel once on a one-body model so its single signature is compiled or loaded."""
    import mujoco

    m = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint name='j' type='hinge'/><geom size='.1' mass='1'/><site name='s'/></body>"
        "</worldbody><actuator><motor joint='j'/></actuator></mujoco>"
    )
    d = mujoco.MjData(m)
    i1, f1 = np.zeros(1, dtype=np.intp), np.zeros(1)
    substeps(
        m._address, d._address, 0, True, False, 0, i1, i1, i1, np.zeros(0, dtype=np.intp), np.zeros(0), np.zeros(0),
        0.0, np.zeros(0), 0.0, np.zeros(3), np.eye(3), np.zeros(6), np.zeros(6), True, f1, f1, f1,
        d.qpos, d.qvel, d.ctrl, d.site_xpos, d.site_xmat, d.qfrc_bias, np.zeros((3, m.nv)), np.zeros((3, m.nv)),
        np.zeros((m.nv, m.nv)),
    )


@njit(nogil=True, cache=True)
def substeps(
    m, d, n, split, skip_first_step1,
    sid, qpos_index, qvel_index, arm_ctrl,
    grip_ctrl, grip_bias, grip_weight, grip_sign, grip_current, grip_speed,
    goal_pos, goal_ori, kp, kd, uncoupling, initial_joint, torque_low, torque_high,
    qpos, qvel, ctrl, site_xpos, site_xmat, qfrc_bias, jacp, jacr, full_mass,
):  # pragma: no cover - compiled
    k = qvel_index.shape[0]
    ee_pos = np.zeros(3)
    ee_ori_mat = np.zeros((3, 3))
    ee_pos_vel = np.zeros(3)
    ee_ori_vel = np.zeros(3)
    joint_pos = np.zeros(k)
    joint_vel = np.zeros(k)
    J_pos = np.zeros((k, 3)).T
    J_ori = np.zeros((k, 3)).T
    J_full = np.zeros((k, 6)).T
    mass_matrix = np.zeros((k, k)).T
    torques = np.zeros(k)
    for i in range(n):
        if not (i == 0 and skip_first_step1):
            if split:
                mj_step1(m, d)
            else:
                mj_forward(m, d)
        # Controller.update()
        for a in range(3):
            ee_pos[a] = site_xpos[sid, a]
            for b in range(3):
                ee_ori_mat[a, b] = site_xmat[sid, 3 * a + b]
        mj_jac_site(m, d, jacp.ctypes.data, jacr.ctypes.data, sid)
        ee_pos_vel = np.dot(jacp, qvel)
        ee_ori_vel = np.dot(jacr, qvel)
        for j in range(k):
            joint_pos[j] = qpos[qpos_index[j]]
            joint_vel[j] = qvel[qvel_index[j]]
            for a in range(3):
                J_pos[a, j] = jacp[a, qvel_index[j]]
                J_ori[a, j] = jacr[a, qvel_index[j]]
                J_full[a, j] = J_pos[a, j]
                J_full[a + 3, j] = J_ori[a, j]
        mj_full_m(m, d, full_mass.ctypes.data)
        for r in range(k):
            for c in range(k):
                mass_matrix[r, c] = full_mass[qvel_index[r], qvel_index[c]]
        # OperationalSpaceController.run_controller (no interpolators)
        ori_error = orientation_error(goal_ori, ee_ori_mat)
        position_error = goal_pos - ee_pos
        vel_pos_error = -ee_pos_vel
        desired_force = np.multiply(position_error, kp[0:3]) + np.multiply(vel_pos_error, kd[0:3])
        vel_ori_error = -ee_ori_vel
        desired_torque = np.multiply(ori_error, kp[3:6]) + np.multiply(vel_ori_error, kd[3:6])
        lambda_full, lambda_pos, lambda_ori, nullspace_matrix = opspace_matrices(mass_matrix, J_full, J_pos, J_ori)
        wrench = np.empty(6)
        if uncoupling:
            wrench[0:3] = np.dot(lambda_pos, desired_force)
            wrench[3:6] = np.dot(lambda_ori, desired_torque)
        else:
            desired_wrench = np.empty(6)
            desired_wrench[0:3] = desired_force
            desired_wrench[3:6] = desired_torque
            wrench = np.dot(lambda_full, desired_wrench)
        torques = np.dot(J_full.T, wrench)
        for j in range(k):
            torques[j] = torques[j] + qfrc_bias[qvel_index[j]]
        # nullspace_torques(joint_kp=10)
        joint_kv = np.sqrt(10) * 2
        pose_torques = np.dot(mass_matrix, (10 * (initial_joint - joint_pos) - joint_kv * joint_vel))
        torques += np.dot(nullspace_matrix.transpose(), pose_torques)
        # SingleArm.control: clip, gripper (PandaGripper.format_action), actuators
        for j in range(k):
            torques[j] = min(max(torques[j], torque_low[j]), torque_high[j])
        for g in range(grip_ctrl.shape[0]):
            step = (-1.0 if g == 0 else 1.0) * grip_speed
            grip_current[g] = min(max(grip_current[g] + step * grip_sign, -1.0), 1.0)
            ctrl[grip_ctrl[g]] = grip_bias[g] + grip_weight[g] * grip_current[g]
        for j in range(k):
            ctrl[arm_ctrl[j]] = torques[j]
        if split:
            mj_step2(m, d)
        else:
            mj_step(m, d)
    return ee_pos, ee_ori_mat, ee_pos_vel, ee_ori_vel, joint_pos, joint_vel, J_pos, J_ori, J_full, mass_matrix, torques
