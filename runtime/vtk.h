// ParaView output without the VTK library: one XML UnstructuredGrid file
// (.vtu) per frame and a .pvd collection listing them with their times.
//
// Points are the model's nodes (anchors included). Cells: the loaded layers'
// surface quads (VTK_QUAD) when the model has them and `surface` is set, and
// one line (VTK_LINE) per always-active spring when `springs` is set.
// Point data: displacement (m, from rest), velocity (m/s), force (N, total
// in the last substep), pin (0 free, 1 fixed, 2 kinematic). Cell data:
// strain (L/L0 - 1 for lines, 0 for quads).
//
// Encodings: ASCII, or raw binary appended data (header_type UInt64,
// little-endian), both readable by ParaView 5. Every file is written through
// AtomicFile; the .pvd is rewritten after each frame, so a series stays
// openable while a run is in progress.
#pragma once

#include "runtime/model.h"
#include "runtime/state.h"

#include <span>
#include <string>
#include <utility>
#include <vector>

namespace orthosim::runtime {

struct VtkOptions {
  bool binary = true;   // false: ASCII
  bool surface = true;  // quads
  bool springs = true;  // lines
};

class VtkSeries {
 public:
  // `dir` must exist; files are <dir>/<name>_<frame>.vtu and <dir>/<name>.pvd.
  VtkSeries(const Model& m, std::string dir, std::string name, VtkOptions o);
  // Re-reads the cells from `m` after a topology edit (an incision).
  void set_topology(const Model& m);
  // Writes one frame of `s` at time s.time and updates the .pvd.
  void write(const Model& m, const State& s);
  int frames() const { return static_cast<int>(files_.size()); }
  std::string pvd_path() const;
  std::int64_t bytes_written() const { return bytes_; }

 private:
  std::string dir_, name_;
  VtkOptions opt_;
  std::vector<std::int64_t> connectivity_, offsets_;
  std::vector<std::uint8_t> types_;
  std::vector<std::int32_t> line_spring_;  // spring of each line cell
  std::int64_t n_quad_cells_ = 0;
  std::vector<std::pair<double, std::string>> files_;
  std::int64_t bytes_ = 0;
};


// Writes a ParaView collection (.pvd) listing (time, file) pairs, atomically.
void write_pvd(const std::string& path, const std::vector<std::pair<double, std::string>>& files);

// Removes the frames of an earlier series from `dir`: the regular files named
// exactly <prefix><digits><extension> (e.g. prefix "tissue_", extension
// ".vtu": tissue_000012.vtu, not tissue_a.vtu, tissue_12.vtp or
// other_000012.vtu), and <pvd> when it is not empty (a file name in `dir`).
// Nothing else is touched. Returns how many files were removed; throws
// Error(file, ...) when a matching file cannot be removed.
int remove_series_frames(const std::string& dir, const std::string& prefix, const std::string& extension,
                         const std::string& pvd = "");

// Whether `file` (a file name) is one a scene's series named `name` writes:
// <name>.pvd and <name>_NNNNNN.vtu, the same for <name>_blood and
// <name>_particles (.vtp frames), <name>_vessels.vtp, <name>_centrelines.vtp,
// <name>_colliders.vtp.
// Other names that start with <name> (tissue_report.json) are not.
bool is_series_file(const std::string& name, const std::string& file);

// ---- PolyData (.vtp), added for the fluid (issue 9) --------------------------

// One point-data array of write_vtp: (n_points x components) values.
struct VtpArray {
  std::string name;
  int components = 1;
  std::vector<double> values;
};

// Writes one XML PolyData file (.vtp) atomically: points (n x 3, m);
// triangles (m x 3) as polygons, or, when there are none, one vertex cell
// per point (a particle cloud); point data arrays (sizes must match, else
// Error). ASCII or raw appended binary as VtkSeries; `time` goes into the
// file's TimeValue field.
void write_vtp(const std::string& path, std::span<const double> points, std::span<const std::int32_t> triangles,
               const std::vector<VtpArray>& point_data, bool binary = true, double time = 0);

}  // namespace orthosim::runtime
