#include "plant_link.h"

#include <arpa/inet.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstring>
#include <stdexcept>

namespace {
constexpr std::size_t CMD_BYTES = 4 + 4 + 8 + 5 * 6 * 8;
constexpr std::size_t STATE_BYTES = 4 + 4 + 3 * 6 * 8;

void put(unsigned char*& p, const void* src, std::size_t n) { std::memcpy(p, src, n); p += n; }
void get(const unsigned char*& p, void* dst, std::size_t n) { std::memcpy(dst, p, n); p += n; }
}  // namespace

PlantLink::PlantLink(const std::string& host, int port, double timeout_s) : timeout_s_(timeout_s) {
    fd_ = ::socket(AF_INET, SOCK_DGRAM, 0);
    if (fd_ < 0) throw std::runtime_error("plant link: cannot create a UDP socket");
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<uint16_t>(port));
    if (::inet_pton(AF_INET, host.c_str(), &addr.sin_addr) != 1)
        throw std::runtime_error("plant link: not an IPv4 address: " + host);
    if (::connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0)
        throw std::runtime_error("plant link: cannot connect to " + host + ":" + std::to_string(port));
}

PlantLink::~PlantLink() {
    if (fd_ >= 0) ::close(fd_);
}

bool PlantLink::exchange(const MotorCommand& cmd, double dt, MotorState& out) {
    unsigned char buf[CMD_BYTES];
    unsigned char* p = buf;
    ++seq_;
    put(p, "Z1C1", 4);
    put(p, &seq_, 4);
    put(p, &dt, 8);
    Joints kp, kd;
    for (std::size_t j = 0; j < NJ; ++j) { kp[j] = cmd.kp[j] * KP_SCALE; kd[j] = cmd.kd[j] * KD_SCALE; }
    const Joints* parts[] = {&cmd.q, &cmd.dq, &cmd.tau, &kp, &kd};
    for (const Joints* v : parts) put(p, v->data(), 6 * 8);
    if (::send(fd_, buf, CMD_BYTES, 0) != static_cast<ssize_t>(CMD_BYTES)) return false;
    pollfd pfd{fd_, POLLIN, 0};
    const int wait_ms = static_cast<int>(timeout_s_ * 1000.0);
    unsigned char in[STATE_BYTES + 16];
    for (;;) {  // drop stale answers (an earlier cycle's) until this cycle's arrives or time runs out
        if (::poll(&pfd, 1, wait_ms) <= 0) return false;
        const ssize_t n = ::recv(fd_, in, sizeof(in), 0);
        if (n != static_cast<ssize_t>(STATE_BYTES) || std::memcmp(in, "Z1S1", 4) != 0) continue;
        std::uint32_t seq;
        std::memcpy(&seq, in + 4, 4);
        if (seq != seq_) continue;
        const unsigned char* q = in + 8;
        get(q, out.q.data(), 48);
        get(q, out.dq.data(), 48);
        get(q, out.tau.data(), 48);
        return true;
    }
}
