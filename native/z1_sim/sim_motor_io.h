// SimMotorIO: simulated Z1 motors behind the vendor controller's IOInterface (darp project code).
//
// z1_ctrl calls sendRecv(cmd, state) at 250 Hz from its FSM thread. This class stands in for the
// motors (IOUDP talks to the real ones): each joint follows the motor law of the command
// (q, dq, tau, kp, kd), limited by the Z1's joint range, speed and torque. See motor_model.h for the
// law and native/z1_sim/README.md for the optional external plant (darp's MuJoCo twin) protocol.
#ifndef DARP_SIM_MOTOR_IO_H
#define DARP_SIM_MOTOR_IO_H

#include <atomic>
#include <chrono>
#include <memory>
#include <string>

#include "interface/IOInterface.h"
#include "motor_model.h"
#include "plant_link.h"

class SimMotorIO : public IOInterface {
public:
    // q0: the joints at power-on; plant: null for the built-in motor model, else the external plant link.
    SimMotorIO(const Joints& q0, MotorParams params, std::unique_ptr<PlantLink> plant, bool verbose);
    ~SimMotorIO();
    bool sendRecv(const LowlevelCmd* cmd, LowlevelState* state) override;
    bool isDisconnect() override { return disconnected_.load(); }

    // Fault injection (set from the control socket thread): the motors stop answering.
    std::atomic<bool> disconnected_{false};

private:
    MotorModel model_;
    std::unique_ptr<PlantLink> plant_;
    bool verbose_;
    bool have_last_ = false;
    bool reported_sizes_ = false;
    std::chrono::steady_clock::time_point last_;
    unsigned long cycles_ = 0;
};

#endif
