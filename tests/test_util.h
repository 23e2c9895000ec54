// Small helpers shared by the tests: scratch directories and running the CLI.
#pragma once

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

}  // namespace orthosim::test
