// Small helpers shared by the tests: scratch directories and running the CLI.
#pragma once

#include <array>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <unistd.h>

namespace orthosim::test {

// A fresh scratch directory, removed at the end of the test.
struct TempDir {
  std::filesystem::path path;
  explicit TempDir(const std::string& tag = "t") {
    static int n = 0;
    path = std::filesystem::temp_directory_path() /
           ("orthosim-" + tag + "-" + std::to_string(::getpid()) + "-" + std::to_string(n++));
    std::filesystem::remove_all(path);
    std::filesystem::create_directories(path);
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path, ec);
  }
  std::string operator/(const std::string& rel) const { return (path / rel).string(); }
};

struct RunResult {
  int code = -1;
  std::string out, err;
};

// Runs the orthosim executable with `args` (a shell-quoted string).
inline RunResult run_cli(const std::string& args) {
  static int n = 0;
  auto dir = std::filesystem::temp_directory_path();
  std::string o = (dir / ("orthosim-cli-out-" + std::to_string(::getpid()) + "-" + std::to_string(n))).string();
  std::string e = (dir / ("orthosim-cli-err-" + std::to_string(::getpid()) + "-" + std::to_string(n++))).string();
  std::string cmd = std::string(ORTHOSIM_BINARY) + " " + args + " >" + o + " 2>" + e;
  int status = std::system(cmd.c_str());
  RunResult r;
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  auto slurp = [](const std::string& p) {
    std::ifstream in(p);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
  };
  r.out = slurp(o);
  r.err = slurp(e);
  std::filesystem::remove(o);
  std::filesystem::remove(e);
  return r;
}

inline std::string read_file(const std::string& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

inline void write_file(const std::string& p, const std::string& text) {
  std::ofstream out(p, std::ios::binary);
  out << text;
}

inline int count_lines(const std::string& s) {
  int n = 0;
  for (char c : s) n += c == '\n';
  return n;
}

// An ASCII STL of the box [lo, hi], its faces' normals outward.
inline std::string box_stl(const std::array<double, 3>& lo, const std::array<double, 3>& hi) {
  auto corner = [&](int c) { return std::array<double, 3>{c & 1 ? hi[0] : lo[0], c & 2 ? hi[1] : lo[1], c & 4 ? hi[2] : lo[2]}; };
  std::string out = "solid box\n";
  for (int axis = 0; axis < 3; ++axis)
    for (int side = 0; side < 2; ++side) {
      // the face's four corners in order around it
      const int a = (axis + 1) % 3, b = (axis + 2) % 3;
      const int base = side << axis;
      const int q[4] = {base, base | 1 << a, base | 1 << a | 1 << b, base | 1 << b};
      const bool flip = side == 0;  // (a, b, axis) is right-handed: counter-clockwise seen from +axis
      for (const auto& t : {std::array<int, 3>{q[0], q[1], q[2]}, std::array<int, 3>{q[0], q[2], q[3]}}) {
        out += "facet normal 0 0 0\nouter loop\n";
        for (int k = 0; k < 3; ++k) {
          const auto v = corner(t[flip ? 2 - k : k]);
          out += "vertex " + std::to_string(v[0]) + " " + std::to_string(v[1]) + " " + std::to_string(v[2]) + "\n";
        }
        out += "endloop\nendfacet\n";
      }
    }
  return out + "endsolid box\n";
}

}  // namespace orthosim::test
