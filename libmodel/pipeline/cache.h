// The stage cache of `orthosim pipeline`: a content-addressed work folder.
//
// Every stage's outputs live in <work>/<stage>/<key>/, where key is a hash of
// everything the outputs depend on: the stage name, the tool version, the
// stage's parameters and the keys of the stages it reads from (or the
// content hashes of external inputs: the slice folder, the tissue table).
// A stage that finishes writes <dir>/manifest.json last, atomically, listing
// each output file with its content hash. An entry is a hit only when its
// manifest exists, names the same key and every listed file still has its
// recorded hash: an interrupted, partial or corrupted entry is detected,
// cleared and rebuilt, never used.
#pragma once

#include <string>
#include <vector>

namespace orthosim::pipeline {

// xxh3 of the parts, each length-prefixed (so ("ab","c") != ("a","bc")), as
// 16 hex digits.
std::string stage_key(const std::string& stage, const std::vector<std::string>& parts);

struct CacheEntry {
  std::string stage, key;
  std::string dir;     // <work>/<stage>/<key>
  bool hit = false;    // valid outputs are there
  std::string reason;  // why a miss: "new", "no manifest", "key mismatch", "<file> changed", ...
};

// Looks the entry up. On a miss the folder is cleared and created empty.
// Throws Error(dir, ...) when the folder cannot be created.
CacheEntry open_entry(const std::string& work, const std::string& stage, const std::string& key);

// Writes the manifest of `outputs` (paths relative to e.dir; files or
// folders) with their hashes. Throws Error(path, ...) if one is missing.
void commit_entry(const CacheEntry& e, const std::vector<std::string>& outputs);

}  // namespace orthosim::pipeline
