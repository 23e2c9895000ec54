#include "libmodel/provenance.h"

#include <xxhash.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <vector>

namespace fs = std::filesystem;

namespace orthosim {

std::string version_string() { return ORTHOSIM_VERSION; }

namespace {
std::string hex(XXH64_hash_t h) {
  char buf[17];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(h));
  return buf;
}

void update_with_file(XXH3_state_t* st, const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  if (!in) throw Error(p.string(), "cannot read file");
  std::vector<char> buf(1 << 20);
  while (in) {
    in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
    if (in.gcount() > 0) XXH3_64bits_update(st, buf.data(), static_cast<std::size_t>(in.gcount()));
  }
}
}  // namespace

std::string hash_bytes(const void* data, std::size_t size) { return hex(XXH3_64bits(data, size)); }

std::string hash_path(const std::string& path) {
  std::error_code ec;
  if (!fs::exists(path, ec)) throw Error(path, "does not exist");
  XXH3_state_t* st = XXH3_createState();
  XXH3_64bits_reset(st);
  try {
    if (fs::is_directory(path, ec)) {
      std::vector<fs::path> files;
      for (auto& e : fs::recursive_directory_iterator(path))
        if (e.is_regular_file()) files.push_back(e.path());
      std::sort(files.begin(), files.end());
      for (auto& f : files) {
        std::string rel = fs::relative(f, path).string();
        XXH3_64bits_update(st, rel.data(), rel.size() + 1);
        update_with_file(st, f);
      }
    } else {
      update_with_file(st, path);
    }
  } catch (...) {
    XXH3_freeState(st);
    throw;
  }
  std::string out = "xxh3:" + hex(XXH3_64bits_digest(st));
  XXH3_freeState(st);
  return out;
}

bool reproducible_run() {
  const char* e = std::getenv("SOURCE_DATE_EPOCH");
  return e != nullptr && *e != 0;
}

std::string now_utc() {
  std::time_t t = std::time(nullptr);
  if (const char* e = std::getenv("SOURCE_DATE_EPOCH"); e != nullptr && *e != 0) {
    // the reproducible-builds convention: seconds since 1970 stand for "now"
    char* end = nullptr;
    const long long v = std::strtoll(e, &end, 10);
    t = (*end == 0 && v >= 0) ? static_cast<std::time_t>(v) : 0;
  }
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

Provenance make_provenance(const std::string& command_line, const std::string& inputs_json,
                           const std::string& parameters_json, std::int64_t seed, double wall_s) {
  Provenance p;
  p.tool_version = version_string();
  p.command_line = command_line;
  p.inputs_json = inputs_json;
  p.parameters_json = parameters_json;
  p.seed = seed;
  p.time_utc = now_utc();
  p.wall_s = reproducible_run() ? 0 : wall_s;
  return p;
}

}  // namespace orthosim
