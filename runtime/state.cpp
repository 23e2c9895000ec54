#include "runtime/state.h"

#include <algorithm>
#include <cstring>

namespace orthosim::runtime {

Vec3 Path::at(Real time) const {
  const std::size_t n = t.size();
  if (n == 0) return {};
  if (time <= t[0]) return load3(p.data(), 0);
  if (time >= t[n - 1]) return load3(p.data(), static_cast<std::int64_t>(n - 1));
  const auto it = std::upper_bound(t.begin(), t.end(), time);
  const auto j = static_cast<std::int64_t>(it - t.begin());  // t[j-1] <= time < t[j]
  const Real w = (time - t[j - 1]) / (t[j] - t[j - 1]);
  const Vec3 a = load3(p.data(), j - 1), b = load3(p.data(), j);
  return a + w * (b - a);
}

Real Path::max_speed() const {
  Real v = 0;
  for (std::size_t j = 1; j < t.size(); ++j) {
    const Real dt = t[j] - t[j - 1];
    if (dt > 0) v = std::max(v, norm(load3(p.data(), j) - load3(p.data(), j - 1)) / dt);
  }
  return v;
}

State make_state(const Model& m) {
  State s;
  const auto n = static_cast<std::size_t>(m.n_nodes);
  s.x = m.rest_x;
  s.v.assign(3 * n, 0);
  s.f.assign(3 * n, 0);
  s.f_ext.assign(3 * n, 0);
  s.warm.assign(3 * n, 0);
  s.pin.assign(n, Pin::free);
  s.inv_mass = m.inv_mass;
  for (std::size_t i = 0; i < n; ++i)
    if (m.inv_mass[i] == 0) s.pin[i] = Pin::fixed;
  return s;
}

void fix_nodes(const Model& m, State& s, std::span<const std::int32_t> nodes) {
  for (auto i : nodes) {
    if (i < 0 || i >= m.n_nodes) continue;
    s.pin[i] = Pin::fixed;
    s.inv_mass[i] = 0;
    for (int k = 0; k < 3; ++k) s.v[3 * i + k] = 0;
  }
  s.step_limit = 0;
}

void release_nodes(const Model& m, State& s, std::span<const std::int32_t> nodes) {
  for (auto i : nodes) {
    if (i < 0 || i >= m.n_nodes || m.inv_mass[i] == 0) continue;  // anchors stay fixed
    s.pin[i] = Pin::free;
    s.inv_mass[i] = m.inv_mass[i];
  }
  s.step_limit = 0;
}

int attach(const Model& m, State& s, Attachment a) {
  if (a.stiffness == 0) {
    for (auto i : a.nodes) {
      if (s.pin[i] == Pin::fixed) continue;  // a fixed node stays where it is
      s.pin[i] = Pin::kinematic;
      s.inv_mass[i] = 0;
    }
  }
  s.attachments.push_back(std::move(a));
  s.step_limit = 0;
  return static_cast<int>(s.attachments.size()) - 1;
}

void detach(const Model& m, State& s, int index) {
  if (index < 0 || index >= static_cast<int>(s.attachments.size())) return;
  Attachment& a = s.attachments[static_cast<std::size_t>(index)];
  if (a.stiffness == 0) {
    for (auto i : a.nodes) {
      if (s.pin[i] != Pin::kinematic) continue;
      s.pin[i] = Pin::free;
      s.inv_mass[i] = m.inv_mass[i];
    }
  }
  a.nodes.clear();
  a.offset.clear();
  // a kinematic node still held by another attachment stays kinematic
  for (const auto& other : s.attachments)
    if (other.stiffness == 0)
      for (auto i : other.nodes)
        if (s.pin[i] == Pin::free) {
          s.pin[i] = Pin::kinematic;
          s.inv_mass[i] = 0;
        }
  s.step_limit = 0;
}

std::uint64_t state_hash(const State& s) {
  std::uint64_t h = 1469598103934665603ull;
  auto mix = [&](const void* data, std::size_t bytes) {
    const auto* p = static_cast<const unsigned char*>(data);
    for (std::size_t i = 0; i < bytes; ++i) {
      h ^= p[i];
      h *= 1099511628211ull;
    }
  };
  mix(&s.time, sizeof s.time);
  mix(s.x.data(), s.x.size() * sizeof(Real));
  mix(s.v.data(), s.v.size() * sizeof(Real));
  return h;
}

}  // namespace orthosim::runtime
