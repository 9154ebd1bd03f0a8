// The simulated Z1 motors: one first-order motor law per joint, with the Z1's limits.
//
// Command (LowlevelCmd, controller units): q, dq (rad, rad/s), tau (Nm), kp, kd (the controller's gain
// units: the motor gains are kp * KP_SCALE Nm/rad and kd * KD_SCALE Nm s/rad, as the vendor's Gazebo
// interface IOROS converts them). The motor's torque is
//     tau_m = clamp(tau + Kp (q_cmd - q) + Kd (dq_cmd - dq), +-tau_max)
// and the joint is a damped load driven by it: the controller's feed-forward torque `tau` is the load it
// expects (gravity, friction), so it balances exactly that load (see MotorModel::step), and the joint
// velocity is the one at which the motor's torque and the load balance:
//     dq = (Kp (q_cmd - q) + Kd dq_cmd + (tau_m_sat - tau_m)) / Kd        (Kd > 0)
// i.e. q follows q_cmd with the first-order lag Kd/Kp (about 0.05 s at the controller's gains), and a
// saturated torque slows the joint down. Velocity is clamped to the joint's speed limit and position to
// its range (hard stop: velocity zeroed there). Kd == 0 and Kp == 0: the joint is free and unloaded
// (the model holds it). `lag_floor_s` adds a minimum lag (a motor's own current loop). A motor that pushes
// a joint into its hard stop at full torque for `stall_trip_s` trips its over-current protection: it
// reports error 0x01 from then on and gives no torque (the joint is held by the hard stop / stays).
#ifndef DARP_MOTOR_MODEL_H
#define DARP_MOTOR_MODEL_H

#include <array>
#include <cstddef>

constexpr std::size_t NJ = 6;
using Joints = std::array<double, NJ>;

constexpr double KP_SCALE = 25.6;    // controller kp -> Nm/rad (vendor sim/IOROS.cpp)
constexpr double KD_SCALE = 0.0128;  // controller kd -> Nm s/rad

struct MotorParams {
    Joints q_min{-2.6179939, 0.0, -2.8797933, -1.5184364, -1.3439035, -2.7925268};
    Joints q_max{2.6179939, 2.9670597, 0.0, 1.5184364, 1.3439035, 2.7925268};
    Joints speed_max{3.1415927, 3.1415927, 3.1415927, 3.1415927, 3.1415927, 3.1415927};
    Joints torque_max{30.0, 60.0, 30.0, 30.0, 30.0, 30.0};
    double lag_floor_s = 0.005;
    double stall_trip_s = 0.25;  // a motor held at a hard stop at full torque this long trips (over-current)
};

struct MotorCommand {
    Joints q{}, dq{}, tau{}, kp{}, kd{};
};

struct MotorState {
    Joints q{}, dq{}, ddq{}, tau{};
    unsigned limit_hits = 0;  // bit j: joint j was at its range limit this step
    std::array<unsigned char, NJ> error{};  // latched motor error per joint (0x01: phase current too large)
};

class MotorModel {
public:
    MotorModel(const Joints& q0, const MotorParams& params);
    // Advance by dt seconds under `cmd`; returns the new state.
    const MotorState& step(const MotorCommand& cmd, double dt);
    const MotorState& state() const { return s_; }
    const MotorParams& params() const { return p_; }

private:
    MotorParams p_;
    MotorState s_;
    Joints stall_s_{};
};

#endif
