#include "libmodel/pipeline/cache.h"

#include "libmodel/format/atomic.h"
#include "libmodel/format/types.h"
#include "libmodel/provenance.h"

#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>
#include <sstream>

namespace orthosim::pipeline {

namespace fs = std::filesystem;
using nlohmann::json;

std::string stage_key(const std::string& stage, const std::vector<std::string>& parts) {
  std::string buf;
  auto add = [&](const std::string& s) { buf += std::to_string(s.size()) + ":" + s + ";"; };
  add(stage);
  for (const auto& p : parts) add(p);
  return hash_bytes(buf.data(), buf.size());
}

namespace {

std::string validity(const std::string& dir, const std::string& key) {
  const fs::path manifest = fs::path(dir) / "manifest.json";
  std::error_code ec;
  if (!fs::is_regular_file(manifest, ec)) return "no manifest (new or interrupted)";
  json m;
  try {
    std::ifstream in(manifest);
    m = json::parse(in);
  } catch (const std::exception&) {
    return "manifest unreadable";
  }
  if (!m.is_object() || !m.contains("key") || !m["key"].is_string() || m["key"].get<std::string>() != key)
    return "key mismatch";
  if (!m.contains("outputs") || !m["outputs"].is_object()) return "manifest without outputs";
  for (const auto& [rel, hash] : m["outputs"].items()) {
    const std::string p = (fs::path(dir) / rel).string();
    if (!fs::exists(p, ec)) return rel + " missing";
    try {
      if (!hash.is_string() || hash_path(p) != hash.get<std::string>()) return rel + " changed";
    } catch (const Error&) {
      return rel + " unreadable";
    }
  }
  return "";
}

}  // namespace

CacheEntry open_entry(const std::string& work, const std::string& stage, const std::string& key) {
  CacheEntry e;
  e.stage = stage;
  e.key = key;
  e.dir = (fs::path(work) / stage / key).string();
  std::error_code ec;
  if (fs::exists(e.dir, ec)) {
    e.reason = validity(e.dir, key);
    e.hit = e.reason.empty();
    if (e.hit) return e;
  } else {
    e.reason = "new";
  }
  fs::remove_all(e.dir, ec);
  fs::create_directories(e.dir, ec);
  if (ec) throw Error(e.dir, "cannot create the cache folder: " + ec.message());
  return e;
}

void commit_entry(const CacheEntry& e, const std::vector<std::string>& outputs) {
  json m;
  m["stage"] = e.stage;
  m["key"] = e.key;
  m["time_utc"] = now_utc();
  m["outputs"] = json::object();
  for (const auto& rel : outputs) {
    const std::string p = (fs::path(e.dir) / rel).string();
    std::error_code ec;
    if (!fs::exists(p, ec)) throw Error(p, "stage output missing");
    m["outputs"][rel] = hash_path(p);
  }
  AtomicFile f((fs::path(e.dir) / "manifest.json").string());
  {
    std::ofstream out(f.temp());
    out << m.dump(2) << "\n";
    if (!out) throw Error(f.target(), "cannot write the manifest");
  }
  f.commit();
}

}  // namespace orthosim::pipeline
