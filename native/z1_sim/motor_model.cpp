#include "motor_model.h"

#include <algorithm>
#include <cmath>

MotorModel::MotorModel(const Joints& q0, const MotorParams& params) : p_(params) {
    for (std::size_t j = 0; j < NJ; ++j) s_.q[j] = std::clamp(q0[j], p_.q_min[j], p_.q_max[j]);
}

const MotorState& MotorModel::step(const MotorCommand& cmd, double dt) {
    s_.limit_hits = 0;
    if (dt <= 0.0) return s_;
    for (std::size_t j = 0; j < NJ; ++j) {
        const double kp = std::max(cmd.kp[j], 0.0) * KP_SCALE;
        const double kd = std::max(cmd.kd[j], 0.0) * KD_SCALE;
        const double q = s_.q[j];
        double v = 0.0;
        double tau_m = 0.0;
        bool saturated = false;
        if (s_.error[j] != 0) {
            v = 0.0;  // a tripped motor gives no torque; the joint stays where it is
        } else if (kd > 0.0) {
            // The velocity at which the PD torque is zero: the feed-forward torque balances the expected load.
            v = (kp * (cmd.q[j] - q) + kd * cmd.dq[j]) / kd;
            // Saturation: the motor cannot give more than torque_max; the torque it lacks slows the joint.
            const double demanded = cmd.tau[j] + kp * (cmd.q[j] - q) + kd * (cmd.dq[j] - v);
            const double given = std::clamp(demanded, -p_.torque_max[j], p_.torque_max[j]);
            v += (given - demanded) / kd;
            tau_m = given;
            if (p_.lag_floor_s > 0.0) {  // the motor's own current loop: velocity cannot change at once
                const double a = 1.0 - std::exp(-dt / p_.lag_floor_s);
                v = s_.dq[j] + (v - s_.dq[j]) * a;
            }
        } else if (kp > 0.0) {  // stiffness without damping: track q_cmd with the motor's own lag
            v = (cmd.q[j] - q) / std::max(p_.lag_floor_s, 1e-3);
            tau_m = cmd.tau[j] + kp * (cmd.q[j] - q);
        } else {
            tau_m = cmd.tau[j];  // pure torque command: balanced by the load it is meant for
        }
        tau_m = std::clamp(tau_m, -p_.torque_max[j], p_.torque_max[j]);
        v = std::clamp(v, -p_.speed_max[j], p_.speed_max[j]);
        double qn = q + v * dt;
        // The hard stops. A motor pushing into one: the PD torque toward the command beyond the stop.
        const double push = kp * (cmd.q[j] - q);
        if (qn <= p_.q_min[j]) {
            qn = p_.q_min[j];
            s_.limit_hits |= 1u << j;
            saturated = -push >= p_.torque_max[j];
        } else if (qn >= p_.q_max[j]) {
            qn = p_.q_max[j];
            s_.limit_hits |= 1u << j;
            saturated = push >= p_.torque_max[j];
        }
        stall_s_[j] = saturated ? stall_s_[j] + dt : 0.0;
        if (stall_s_[j] >= p_.stall_trip_s) s_.error[j] = 0x01;
        const double vn = (qn - q) / dt;
        s_.ddq[j] = (vn - s_.dq[j]) / dt;
        s_.dq[j] = vn;
        s_.q[j] = qn;
        s_.tau[j] = tau_m;
    }
    return s_;
}
