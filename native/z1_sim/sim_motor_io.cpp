#include "sim_motor_io.h"

#include <algorithm>
#include <iomanip>
#include <iostream>

SimMotorIO::SimMotorIO(const Joints& q0, MotorParams params, std::unique_ptr<PlantLink> plant, bool verbose)
    : model_(q0, params), plant_(std::move(plant)), verbose_(verbose) {
    hasGripper = false;
    hasErrorState = false;
    lowCmd = nullptr;   // created by CtrlComponents::geneObj
    lowState = nullptr;
    std::cout << "[darp-sim] simulated motors (" << (plant_ ? "external plant" : "built-in motor model")
              << "), no gripper" << std::endl;
}

SimMotorIO::~SimMotorIO() = default;

bool SimMotorIO::sendRecv(const LowlevelCmd* cmd, LowlevelState* state) {
    const auto now = std::chrono::steady_clock::now();
    double dt = 0.004;
    if (have_last_) dt = std::clamp(std::chrono::duration<double>(now - last_).count(), 0.0, 0.02);
    last_ = now;
    have_last_ = true;
    if (disconnected_.load()) return false;  // the motors stopped answering: state left as it was

    MotorCommand c;
    const std::size_t n = std::min<std::size_t>(NJ, cmd->q.size());
    for (std::size_t j = 0; j < n; ++j) {
        c.q[j] = cmd->q[j];
        c.dq[j] = cmd->dq[j];
        c.tau[j] = cmd->tau[j];
        c.kp[j] = cmd->kp[j];
        c.kd[j] = cmd->kd[j];
    }
    MotorState s = model_.state();
    if (plant_) {
        if (!plant_->exchange(c, dt, s)) {
            if (verbose_) std::cout << "[darp-sim] plant did not answer" << std::endl;
            return false;
        }
    } else {
        s = model_.step(c, dt);
    }
    for (std::size_t j = 0; j < NJ && j < state->q.size(); ++j) {
        state->q[j] = s.q[j];
        state->dq[j] = s.dq[j];
        state->ddq[j] = s.ddq[j];
        state->tau[j] = s.tau[j];
    }
    // Motor errors: the arm's motors in joint order (joint2 is driven by two motors on the real arm; both
    // report the joint's error when the lists are longer than six).
    for (std::size_t m = 0; m < state->errorstate.size(); ++m) state->errorstate[m] = s.error[std::min(m, NJ - 1)];
    for (auto& c2 : state->isMotorConnected) c2 = 0;
    if (!reported_sizes_) {
        reported_sizes_ = true;
        if (verbose_) std::cout << "[darp-sim] state sizes: q " << state->q.size() << ", errorstate "
                                << state->errorstate.size() << ", isMotorConnected " << state->isMotorConnected.size()
                                << std::endl;
    }
    for (auto& t : state->temperature) t = 35;
    ++cycles_;
    if (verbose_ && cycles_ % 250 == 0) {
        std::cout << std::setprecision(4) << "[darp-sim] q";
        for (std::size_t j = 0; j < NJ; ++j) std::cout << ' ' << s.q[j];
        std::cout << " | cmd q";
        for (std::size_t j = 0; j < NJ; ++j) std::cout << ' ' << c.q[j];
        std::cout << " dq";
        for (std::size_t j = 0; j < NJ; ++j) std::cout << ' ' << c.dq[j];
        std::cout << " tau";
        for (std::size_t j = 0; j < NJ; ++j) std::cout << ' ' << c.tau[j];
        std::cout << " kp";
        for (std::size_t j = 0; j < NJ; ++j) std::cout << ' ' << c.kp[j];
        std::cout << " kd";
        for (std::size_t j = 0; j < NJ; ++j) std::cout << ' ' << c.kd[j];
        std::cout << std::endl;
    }
    return true;
}
