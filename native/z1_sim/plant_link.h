// PlantLink: the optional external plant (darp's MuJoCo twin in a Python process) over local UDP.
//
// Each controller cycle the IO class sends one command datagram and waits (up to timeout) for one state
// datagram; the plant integrates its physics for the command's dt and answers with the joints it
// reached. Little-endian, packed (see native/z1_sim/README.md, "External plant"):
//   command: magic "Z1C1", u32 seq, f64 dt, f64 q[6], dq[6], tau[6], kp[6], kd[6]   (5*48 + 16 bytes)
//   state:   magic "Z1S1", u32 seq, f64 q[6], dq[6], tau[6]                          (3*48 + 8 bytes)
// kp and kd are in the motor's own units (Nm/rad, Nm s/rad): the controller's gains already scaled.
#ifndef DARP_PLANT_LINK_H
#define DARP_PLANT_LINK_H

#include <cstdint>
#include <string>

#include "motor_model.h"

class PlantLink {
public:
    PlantLink(const std::string& host, int port, double timeout_s);
    ~PlantLink();
    // Exchange one command for one state; false when the plant did not answer in time.
    bool exchange(const MotorCommand& cmd, double dt, MotorState& out);

private:
    int fd_ = -1;
    std::uint32_t seq_ = 0;
    double timeout_s_;
};

#endif
