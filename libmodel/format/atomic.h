// Atomic outputs: write to a temporary name beside the target, rename on
// success. An interrupted or failed run never leaves a truncated file, and a
// pre-existing output stays untouched until the new one is complete.
#pragma once

#include <string>
#include <vector>

namespace orthosim {

// One output file. Write to temp(), then commit(). The destructor removes
// the temporary file if commit() was not reached.
class AtomicFile {
 public:
  explicit AtomicFile(std::string target);
  ~AtomicFile();
  AtomicFile(const AtomicFile&) = delete;
  AtomicFile& operator=(const AtomicFile&) = delete;
  const std::string& temp() const { return temp_; }
  const std::string& target() const { return target_; }
  void commit();  // throws Error(target, ...) if the rename fails

 private:
  std::string target_, temp_;
  bool committed_ = false;
};

// An output directory. Files go into temp() (a sibling directory); commit()
// moves each file into the target directory (created if missing), each move
// atomic. The target must not be an existing non-directory. The destructor
// removes the temporary directory if commit() was not reached.
class AtomicDir {
 public:
  explicit AtomicDir(std::string target);
  ~AtomicDir();
  AtomicDir(const AtomicDir&) = delete;
  AtomicDir& operator=(const AtomicDir&) = delete;
  const std::string& temp() const { return temp_; }
  const std::string& target() const { return target_; }
  std::string temp_path(const std::string& relative) const { return temp_ + "/" + relative; }
  void commit();

 private:
  std::string target_, temp_;
  bool committed_ = false;
};

// Throws Error(path, ...) when `path` exists and is not a directory, or
// cannot be created as one. Used to validate --out DIR before any work.
void check_output_dir(const std::string& path);
// Throws Error(path, ...) when the directory that would hold `path` does not
// exist or `path` is an existing directory.
void check_output_file(const std::string& path);

// Removes every temporary output (AtomicFile, AtomicDir) of this process not
// yet committed or destroyed. For tools/main's signal thread: an interrupted
// run (Ctrl-C, SIGTERM) leaves no temporary file beside its outputs (an
// interrupted build left a 300 MB one). Thread-safe.
void remove_uncommitted_outputs();

// Writes `text` atomically to `path`.
void write_text_file(const std::string& path, const std::string& text);

}  // namespace orthosim
