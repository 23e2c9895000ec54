#include "libmodel/format/atomic.h"

#include "libmodel/format/types.h"

#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <set>
#include <system_error>

namespace fs = std::filesystem;

namespace orthosim {
namespace {

std::string temp_name(const std::string& target) {
  static std::atomic<int> counter{0};
  fs::path t(target);
  // appended piece by piece: GCC 12's "." + std::string (an insert at 0 on an
  // rvalue) raised a false -Wrestrict warning inside <string> (GCC bug 105329)
  std::string name = ".";
  name += t.filename().string();
  name += ".tmp-" + std::to_string(::getpid()) + "-" + std::to_string(counter++);
  return (t.parent_path() / name).string();
}

// the temporaries alive now (never destroyed: the signal thread may use it at exit)
std::mutex& temps_mutex() {
  static auto* m = new std::mutex;
  return *m;
}
std::set<std::string>& temps() {
  static auto* s = new std::set<std::string>;
  return *s;
}
void track(const std::string& temp) {
  std::lock_guard<std::mutex> lock(temps_mutex());
  temps().insert(temp);
}
void untrack(const std::string& temp) {
  std::lock_guard<std::mutex> lock(temps_mutex());
  temps().erase(temp);
}

}  // namespace

void remove_uncommitted_outputs() {
  std::lock_guard<std::mutex> lock(temps_mutex());
  for (const std::string& t : temps()) {
    std::error_code ec;
    fs::remove_all(t, ec);
  }
  temps().clear();
}

void check_output_file(const std::string& path) {
  if (path.empty()) throw Error(path, "empty output path");
  fs::path p(path);
  std::error_code ec;
  if (fs::is_directory(p, ec)) throw Error(path, "output path is a directory");
  fs::path parent = p.parent_path();
  if (!parent.empty() && !fs::is_directory(parent, ec))
    throw Error(path, "output directory " + parent.string() +
                          (fs::exists(parent, ec) ? " is not a directory" : " does not exist"));
}

void check_output_dir(const std::string& path) {
  if (path.empty()) throw Error(path, "empty output directory");
  std::error_code ec;
  if (fs::exists(path, ec) && !fs::is_directory(path, ec))
    throw Error(path, "output path exists and is not a directory");
  fs::path parent = fs::path(path).parent_path();
  // (a parent that is a file passed here, and tune failed at its end, after it had updated the model)
  for (fs::path up = parent; !up.empty(); up = up.parent_path()) {
    if (fs::exists(up, ec)) {
      if (!fs::is_directory(up, ec)) throw Error(path, up.string() + " is not a directory");
      break;
    }
    if (up == up.parent_path()) break;
  }
  if (!parent.empty() && !fs::exists(parent, ec)) {
    fs::create_directories(parent, ec);
    if (ec) throw Error(path, "cannot create parent directory: " + ec.message());
  }
}

AtomicFile::AtomicFile(std::string target) : target_(std::move(target)) {
  check_output_file(target_);
  temp_ = temp_name(target_);
  track(temp_);
}

AtomicFile::~AtomicFile() {
  if (!committed_) {
    std::error_code ec;
    fs::remove(temp_, ec);
  }
  untrack(temp_);
}

void AtomicFile::commit() {
  std::error_code ec;
  fs::rename(temp_, target_, ec);
  if (ec) throw Error(target_, "cannot move output into place: " + ec.message());
  committed_ = true;
  untrack(temp_);
}

AtomicDir::AtomicDir(std::string target) : target_(std::move(target)) {
  check_output_dir(target_);
  std::string t = target_;
  while (t.size() > 1 && t.back() == '/') t.pop_back();
  target_ = t;
  temp_ = temp_name(target_);
  track(temp_);
  std::error_code ec;
  fs::create_directories(temp_, ec);
  if (ec) throw Error(target_, "cannot create temporary directory: " + ec.message());
}

AtomicDir::~AtomicDir() {
  if (!committed_) {
    std::error_code ec;
    fs::remove_all(temp_, ec);
  }
  untrack(temp_);
}

void AtomicDir::commit() {
  std::error_code ec;
  if (!fs::exists(target_, ec)) {
    fs::rename(temp_, target_, ec);
    if (ec) throw Error(target_, "cannot move output directory into place: " + ec.message());
    committed_ = true;
    return;
  }
  // merge: move each entry, replacing what is there. First check that no entry
  // is blocked (a folder where a file goes, a file where a folder goes), so that
  // a merge that cannot finish moves nothing (tune's plot blocked by a folder of
  // its name failed half-way, after the model had been committed)
  for (auto it = fs::recursive_directory_iterator(temp_); it != fs::recursive_directory_iterator(); ++it) {
    const fs::path dst = fs::path(target_) / fs::relative(it->path(), temp_);
    const fs::file_status st = fs::symlink_status(dst, ec);
    if (!fs::exists(st)) continue;
    if (it->is_directory() && !fs::is_directory(st))
      throw Error(dst.string(), "cannot move output into place: a file is in the way of a folder");
    if (!it->is_directory() && fs::is_directory(st))
      throw Error(dst.string(), "cannot move output into place: a folder is in the way of a file");
  }
  for (auto it = fs::recursive_directory_iterator(temp_); it != fs::recursive_directory_iterator(); ++it) {
    fs::path rel = fs::relative(it->path(), temp_);
    fs::path dst = fs::path(target_) / rel;
    if (it->is_directory()) {
      fs::create_directories(dst, ec);
      if (ec) throw Error(dst.string(), "cannot create directory: " + ec.message());
    } else {
      fs::rename(it->path(), dst, ec);
      if (ec) throw Error(dst.string(), "cannot move output into place: " + ec.message());
    }
  }
  committed_ = true;
  fs::remove_all(temp_, ec);
}

void write_text_file(const std::string& path, const std::string& text) {
  AtomicFile out(path);
  {
    std::ofstream f(out.temp(), std::ios::binary);
    f << text;
    f.flush();
    if (!f) throw Error(path, "cannot write file");
  }
  out.commit();
}

}  // namespace orthosim
