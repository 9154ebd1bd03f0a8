// z1_ctrl with simulated motors (darp project code): the vendor's z1_controller main.cpp (BSD-3-Clause,
// Unitree Robotics) with its motor side replaced and its SDK ports taken from the command line.
//
// The vendor main creates `new IOUDP(ctrl_IP, ctrl_port)` (the arm's lower computer over UDP) and
// `new ARMSDK(events, emptyAction, "127.0.0.1", 8072, 8071, 0.002)` (the SDK link: it sends to 8072 and
// listens on 8071). Here the motors are SimMotorIO and both SDK ports are options, so that two
// controllers (two arms) run side by side. Everything else (FSM states, CtrlComponents, the closed
// libZ1 logic) is the vendor's, unchanged. It does not switch itself to SCHED_FIFO (the vendor main
// does, for the real arm): a simulated arm must not starve a shared machine.
//
// Usage: z1_ctrl_sim [--sdk-port 8071] [--client-port 8072] [--q0 q1,...,q6] [--plant HOST:PORT]
//                    [--plant-timeout-s 0.1] [--lag-floor-s 0.005] [--joint-range J:LO:HI]...
//                    [--exit-with-parent] [--verbose]
// Run it from a folder whose parent holds config/ (config.xml, savedArmStates.csv), as the vendor's
// z1_ctrl is run from build/ beside config/. SIGUSR1 toggles a motor link loss (the motors stop
// answering), SIGINT/SIGTERM end it.
#include <sys/prctl.h>
#include <unistd.h>

#include <csignal>
#include <cstdlib>
#include <cstring>
#include <iostream>
#include <memory>
#include <sstream>
#include <string>

#include "FSM/FiniteStateMachine.h"
#include "FSM/State_BackToStart.h"
#include "FSM/State_Calibration.h"
#include "FSM/State_Cartesian.h"
#include "FSM/State_JointSpace.h"
#include "FSM/State_LowCmd.h"
#include "FSM/State_MoveC.h"
#include "FSM/State_MoveJ.h"
#include "FSM/State_MoveL.h"
#include "FSM/State_Passive.h"
#include "FSM/State_SaveState.h"
#include "FSM/State_Teach.h"
#include "FSM/State_TeachRepeat.h"
#include "FSM/State_ToState.h"
#include "FSM/State_Trajectory.h"
#include "sim_motor_io.h"

namespace {
volatile std::sig_atomic_t g_running = 1;
volatile std::sig_atomic_t g_toggle_link = 0;
bool running = true;  // the vendor's CtrlComponents keeps a pointer to it

struct Options {
    unsigned sdk_port = 8071;     // the controller listens here for the SDK
    unsigned client_port = 8072;  // the SDK listens here (the controller sends here)
    Joints q0{0.0, 0.0, -0.005, -0.074, 0.0, 0.0};  // startFlat: where a Z1 rests at power-on
    std::string plant_host;
    int plant_port = 0;
    double plant_timeout_s = 0.1;
    double lag_floor_s = 0.005;
    bool verbose = false;
    bool exit_with_parent = false;  // end when the process that started it ends (tests, darp hardware vendor-sim)
    MotorParams params;
};

[[noreturn]] void usage(const std::string& why) {
    std::cerr << "z1_ctrl_sim: " << why << "\nusage: z1_ctrl_sim [--sdk-port P] [--client-port P] "
              << "[--q0 q1,...,q6] [--plant HOST:PORT] [--plant-timeout-s S] [--lag-floor-s S] "
              << "[--joint-range J:LO:HI]... [--exit-with-parent] [--verbose]"
              << std::endl;
    std::exit(2);
}

unsigned port_arg(const char* text, const char* name) {
    char* end = nullptr;
    const long v = std::strtol(text, &end, 10);
    if (*end != '\0' || v < 1 || v > 65535) usage(std::string(name) + ": not a port: " + text);
    return static_cast<unsigned>(v);
}

double number_arg(const char* text, const char* name) {
    char* end = nullptr;
    const double v = std::strtod(text, &end);
    if (*end != '\0') usage(std::string(name) + ": not a number: " + text);
    return v;
}

Options parse(int argc, char** argv) {
    Options o;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        auto value = [&]() -> const char* {
            if (i + 1 >= argc) usage(a + " needs a value");
            return argv[++i];
        };
        if (a == "--sdk-port") o.sdk_port = port_arg(value(), "--sdk-port");
        else if (a == "--client-port") o.client_port = port_arg(value(), "--client-port");
        else if (a == "--plant-timeout-s") o.plant_timeout_s = number_arg(value(), "--plant-timeout-s");
        else if (a == "--lag-floor-s") o.lag_floor_s = number_arg(value(), "--lag-floor-s");
        else if (a == "--verbose") o.verbose = true;
        else if (a == "--exit-with-parent") o.exit_with_parent = true;
        else if (a == "--joint-range") {  // J:LO:HI, joint 1..6: a narrower hard stop (a cable, a fixture)
            std::stringstream ss(value());
            std::string j, lo, hi;
            if (!std::getline(ss, j, ':') || !std::getline(ss, lo, ':') || !std::getline(ss, hi))
                usage("--joint-range needs J:LO:HI");
            const int k = static_cast<int>(number_arg(j.c_str(), "--joint-range")) - 1;
            if (k < 0 || k >= static_cast<int>(NJ)) usage("--joint-range: joint must be 1..6");
            o.params.q_min[k] = number_arg(lo.c_str(), "--joint-range");
            o.params.q_max[k] = number_arg(hi.c_str(), "--joint-range");
            if (o.params.q_min[k] >= o.params.q_max[k]) usage("--joint-range: LO must be below HI");
        }
        else if (a == "--q0") {
            std::stringstream ss(value());
            std::string item;
            std::size_t j = 0;
            while (std::getline(ss, item, ',')) {
                if (j >= NJ) usage("--q0 needs 6 comma-separated angles");
                o.q0[j++] = number_arg(item.c_str(), "--q0");
            }
            if (j != NJ) usage("--q0 needs 6 comma-separated angles");
        } else if (a == "--plant") {
            const std::string hp = value();
            const auto colon = hp.rfind(':');
            if (colon == std::string::npos) usage("--plant needs HOST:PORT");
            o.plant_host = hp.substr(0, colon);
            o.plant_port = static_cast<int>(port_arg(hp.c_str() + colon + 1, "--plant"));
        } else usage("unknown option " + a);
    }
    if (o.sdk_port == o.client_port) usage("--sdk-port and --client-port must differ");
    return o;
}
}  // namespace

int main(int argc, char** argv) {
    const Options opt = parse(argc, argv);
    if (opt.exit_with_parent) {
        ::prctl(PR_SET_PDEATHSIG, SIGTERM);
        if (::getppid() == 1) return 0;  // the parent is already gone
    }
    std::cout << std::fixed << std::setprecision(5);

    EmptyAction emptyAction((int)ArmFSMStateName::INVALID);
    std::vector<KeyAction*> events;
    char* vendor_argv[] = {argv[0], nullptr};  // the vendor's own options are not used here
    CtrlComponents* ctrlComp = new CtrlComponents(1, vendor_argv);

    ctrlComp->dt = 1.0 / 250.;
    ctrlComp->armConfigPath = "../config/";
    ctrlComp->stateCSV = new CSVTool("../config/savedArmStates.csv");
    MotorParams params = opt.params;
    params.lag_floor_s = opt.lag_floor_s;
    std::unique_ptr<PlantLink> plant;
    if (opt.plant_port != 0) plant = std::make_unique<PlantLink>(opt.plant_host, opt.plant_port, opt.plant_timeout_s);
    SimMotorIO* io = new SimMotorIO(opt.q0, params, std::move(plant), opt.verbose);
    ctrlComp->ioInter = io;
    ctrlComp->geneObj();
    ctrlComp->cmdPanel = new ARMSDK(events, emptyAction, "127.0.0.1", opt.client_port, opt.sdk_port, 0.002);
    std::cout << "[darp-sim] SDK link: listening on " << opt.sdk_port << ", sending to 127.0.0.1:"
              << opt.client_port << std::endl;

    std::vector<FSMState*> states;
    states.push_back(new State_Passive(ctrlComp));
    states.push_back(new State_BackToStart(ctrlComp));
    states.push_back(new State_JointSpace(ctrlComp));
    states.push_back(new State_Cartesian(ctrlComp));
    states.push_back(new State_MoveJ(ctrlComp));
    states.push_back(new State_MoveL(ctrlComp));
    states.push_back(new State_MoveC(ctrlComp));
    states.push_back(new State_LowCmd(ctrlComp));
    states.push_back(new State_SaveState(ctrlComp));
    states.push_back(new State_Teach(ctrlComp));
    states.push_back(new State_TeachRepeat(ctrlComp));
    states.push_back(new State_ToState(ctrlComp));
    states.push_back(new State_Trajectory(ctrlComp));
    states.push_back(new State_Calibration(ctrlComp));

    FiniteStateMachine* fsm = new FiniteStateMachine(states, ctrlComp);
    ctrlComp->running = &running;
    std::signal(SIGINT, [](int) { g_running = 0; });
    std::signal(SIGTERM, [](int) { g_running = 0; });
    std::signal(SIGUSR1, [](int) { g_toggle_link = 1; });
    std::this_thread::sleep_for(std::chrono::seconds(1));
    ctrlComp->cmdPanel->start();
    std::cout << "[darp-sim] ready" << std::endl;
    while (g_running) {
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        if (g_toggle_link) {
            g_toggle_link = 0;
            const bool lost = !io->disconnected_.load();
            io->disconnected_.store(lost);
            std::cout << "[darp-sim] motor link " << (lost ? "lost" : "restored") << std::endl;
        }
    }
    running = false;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    delete fsm;
    delete ctrlComp;
    return 0;
}
