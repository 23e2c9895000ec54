// Provenance helpers: version string, content hashes of inputs, UTC time.
#pragma once

#include "libmodel/format/model.h"

#include <string>

namespace orthosim {

std::string version_string();  // e.g. "0.1.0"

// "xxh3:<16 hex digits>" of a file's bytes, or of a directory's regular files
// (names and contents, in sorted order). Throws Error(path, ...) if unreadable.
std::string hash_path(const std::string& path);
// xxh3-64 of a byte buffer as 16 hex digits.
std::string hash_bytes(const void* data, std::size_t size);

// ISO 8601, seconds. With SOURCE_DATE_EPOCH set (the reproducible-builds
// convention: seconds since 1970) that time instead of the clock's.
std::string now_utc();
// SOURCE_DATE_EPOCH is set: files record no wall time (provenance wall_s and
// /tuning seconds are 0), so the same inputs give the same bytes.
bool reproducible_run();

// A Provenance record for `stage` with version, time and command line filled.
Provenance make_provenance(const std::string& command_line, const std::string& inputs_json,
                           const std::string& parameters_json, std::int64_t seed, double wall_s);

}  // namespace orthosim
