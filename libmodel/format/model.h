// The orthosim model file: one HDF5 file per model that every stage writes
// into and the runtime reads from. docs/model-format.md is the user-facing
// description; this header is the single declaration of every field.
//
// Each group type is a plain struct. Its fields are declared once, in its
// `fields()` visitor: name, count (rows), unit and meaning. Writing, reading,
// shape and dtype checks and equality in tests are all driven from there.
// Widths and element types come from the member's C++ type.
//
// Frames and units: SI throughout (m, kg, s, Pa, N/m). Positions are in the
// physical frame of the image stack: x along image columns, y along image
// rows, z along slices, origin at the centre of voxel (0,0,0) plus origin_m.
#pragma once

#include "libmodel/format/atomic.h"
#include "libmodel/format/h5file.h"
#include "libmodel/format/types.h"

#include <array>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

namespace orthosim {

inline constexpr int kFormatMajor = 1;
inline constexpr int kFormatMinor = 0;
std::string format_version();  // "MAJOR.MINOR"

// ---- /volume: the tissue label volume --------------------------------------
// The voxel geometry every stage takes: sizes from 1 um to 10 cm, an origin
// within 1 km. Beyond, nothing is a cryosection stack, and the stages'
// arithmetic overflows or divides by zero (a spacing of 1e300 m was segmented
// and then crashed surface with a floating-point exception and vessels with a
// segmentation fault). Returns "" when valid, else the problem, e.g.
// "spacing along x is 1e+300 m: each voxel size must be in [1e-06, 0.1] m".
inline constexpr double kMinVoxelSpacingM = 1e-6, kMaxVoxelSpacingM = 0.1, kMaxOriginM = 1e3;
std::string voxel_geometry_problem(const std::array<double, 3>& spacing_m, const std::array<double, 3>& origin_m);

struct Volume {
  int nx = 0, ny = 0, nz = 0;
  std::array<double, 3> spacing_m{1e-3, 1e-3, 1e-3};  // voxel size along x, y, z
  std::array<double, 3> origin_m{0, 0, 0};            // centre of voxel (0,0,0)
  std::vector<std::uint8_t> labels;  // nz*ny*nx, x fastest: labels[(z*ny + y)*nx + x]
  std::vector<std::string> label_names;  // label_names[v] names label value v; [0] = "background"

  std::size_t index(int x, int y, int z) const {
    return (static_cast<std::size_t>(z) * ny + y) * nx + x;
  }
  std::uint8_t at(int x, int y, int z) const { return labels[index(x, y, z)]; }
  // Physical position of a voxel centre (m).
  Eigen::Vector3d position(double x, double y, double z) const {
    return {origin_m[0] + x * spacing_m[0], origin_m[1] + y * spacing_m[1], origin_m[2] + z * spacing_m[2]};
  }
  int label_of(const std::string& name) const;  // -1 if absent
};

// ---- /surfaces/<tissue>: closed triangle surface ---------------------------
struct Surface {
  MatX3d vertices;  // (n_vertices x 3) m
  MatX3i faces;     // (n_faces x 3) vertex ids, counter-clockwise seen from outside

  template <class V> void fields(V&& v) {
    v(vertices, "vertices", "n_vertices", "m", "vertex positions (n_vertices x 3), physical frame");
    v(faces, "faces", "n_faces", "1", "triangles (n_faces x 3), vertex ids, outward counter-clockwise");
  }
};

// ---- /quads/<tissue>: structured quad surface from remesh -------------------
// An nu x nv grid: nu points around each ring (periodic), nv rings along the
// limb axis. Vertex (i, j) is row j*nu + i.
struct QuadSurface {
  int nu = 0, nv = 0;
  MatX3d vertices;  // (nu*nv x 3) m
  MatX4i quads;     // (n_quads x 4) vertex ids, counter-clockwise seen from outside
  MatX2d uv;        // (nu*nv x 2) texture coordinates in [0,1]

  template <class V> void fields(V&& v) {
    v(vertices, "vertices", "n_vertices", "m", "grid vertices (nu*nv x 3), row j*nu+i");
    v(quads, "quads", "n_quads", "1", "quads (n_quads x 4), vertex ids, outward counter-clockwise");
    v(uv, "uv", "n_vertices", "1", "texture coordinates (nu*nv x 2) in [0,1]");
  }
};

// ---- /layers/<name>: one layer of the multilayer mass-spring model ---------
// Node ids are global: a layer owns nodes node_offset .. node_offset+n_nodes-1
// and its springs, tets and quads may reference nodes of the neighbouring
// layers (the surface between two layers is owned by exactly one of them).
//
// A biphasic spring (k1, turning_length, k2) exerts, at length L from rest L0:
//   f = k1 (L - L0)                            for L <  Lt
//   f = k1 (L - L0) + (k2 - k1) (L - Lt)       for L >= Lt
// so k2 is the total slope past the turning point (paper §4.1, Table 1). It is
// decomposed for the linear-only solver into two linear springs in parallel:
// (k1, rest L0) always active, and (k2 - k1, rest Lt) slack below Lt.
// A linear spring has k2 == k1 and turning_length == rest_length (no second
// spring is emitted).
enum class SpringClass : std::uint8_t { structural = 0, shear = 1, inter_layer = 2, body = 3 };

struct Layer {
  std::string tissue;     // tissue name in the tissue table
  std::string kind;       // "tetra" | "lattice" | "rigid"
  int order = 0;          // 0 = outermost
  std::int64_t node_offset = 0;

  MatX3d nodes;           // (n_nodes x 3) m, rest positions
  VecXd masses;           // (n_nodes) kg
  MatX2i springs;         // (n_springs x 2) global node ids
  VecXd rest_length;      // (n_springs) m
  VecXu8 spring_class;    // (n_springs) SpringClass
  VecXd k1;               // (n_springs) N/m, first-phase stiffness
  VecXd k2;               // (n_springs) N/m, second-phase (total) stiffness
  VecXd turning_length;   // (n_springs) m
  VecXd damping;          // (n_springs) N s/m
  MatX2i lin_springs;     // (n_lin x 2) global node ids: the linear decomposition
  VecXd lin_rest_length;  // (n_lin) m
  VecXd lin_k;            // (n_lin) N/m
  VecXd lin_damping;      // (n_lin) N s/m
  VecXu8 lin_slack;       // (n_lin) 1: acts only when stretched beyond its rest length
  MatX4i tets;            // (n_tets x 4) global node ids (tetra layers: 7 per prism; lattice layers with a volume term or the inversion guard: 6 per hexahedron)
  MatX4i quads;           // (n_quads x 4) global node ids of this layer's top surface
  // The law its springs follow, per spring class (structural, shear,
  // inter-layer, body) k1 Pa, turning strain, k2 Pa (12 values; every spring
  // s of class c has k1 = k1_c k_per_pa(s), k2 = k2_c k_per_pa(s), turning
  // length L0 (1 + t_c)): written by build (the tissue table's law in every
  // class) and by tune (the tuned laws); attribute "spring_law" of the layer
  // group. Empty in rigid layers and in files written before 2026-11-27.
  std::vector<double> spring_law;
  // The volume term (docs/msm.md, "The volume term"): each group of
  // volume_group consecutive rows of `tets`, of summed rest volume V0, adds
  // the energy (volume_modulus / 2) (V - V0)^2 / |V0| with V their summed
  // signed volume, so the layer resists compression and folding through
  // itself like a tissue of Poisson's ratio near 0.5, not the 1/4 of central
  // springs alone. A tetra layer's groups are its tetrahedra (volume_group
  // 1); a lattice layer's are its hexahedra, 6 tetrahedra each (volume_group
  // 6: one pressure per cell, which does not lock). Pa; 0 = none (rigid
  // layers, and files written before 2026-11-28; lattice layers before
  // 2026-11-28 (2)). Attributes "volume_modulus" and "volume_group" (absent:
  // 1) of the layer group; written by build (from --poisson-ratio and the
  // law's K1) and rescaled by tune with K1.
  double volume_modulus = 0;
  int volume_group = 1;
  // The volume term's own tetrahedra, where they are not `tets`: a tetra
  // layer built with --tetra-volume-term prisms holds its grid prisms and
  // their caps here (msm::grid_prism_tets: under each triangle of a quad the
  // 3 tetrahedra of its 6 grid nodes with the cap of its projected centroid
  // reversed, then with it, volume_group 4), and the inversion guard keeps
  // `tets`. Empty: the term's groups are rows of
  // `tets`. Optional dataset "volume_tets" (n x 4, global ids; files before
  // 2026-11-29 have none).
  MatX4i volume_tets;
  // The inversion guard (docs/msm.md, "The inversion guard"): each row of
  // `tets`, of signed rest volume V0 (s its sign), adds (guard_modulus / 2)
  // min(0, s V - guard_ratio |V0|)^2 / |V0|: nothing until the tetrahedron
  // has lost 1 - guard_ratio of its volume, then the tissue's bulk modulus
  // against more, so a layer resists turning inside out while the
  // small-strain response the tables and the calibration see is the
  // springs' and the volume term's alone. Pa; 0 = none (files written before 2026-11-28 (3),
  // rigid layers, build's --inversion-guard 0). Attributes "guard_modulus"
  // and "guard_ratio" (in (0, 1)) of the layer group; written by build (the
  // bulk modulus K1 / (3 (1 - 2 nu))) and rescaled by tune with K1.
  double guard_modulus = 0;
  double guard_ratio = 0;

  template <class V> void fields(V&& v) {
    v(nodes, "nodes", "n_nodes", "m", "rest positions (n_nodes x 3)");
    v(masses, "masses", "n_nodes", "kg", "lumped node masses (n_nodes)");
    v(springs, "springs", "n_springs", "1", "spring end nodes (n_springs x 2), global ids");
    v(rest_length, "rest_length", "n_springs", "m", "rest lengths (n_springs)");
    v(spring_class, "spring_class", "n_springs", "1", "0 structural, 1 shear, 2 inter-layer, 3 body");
    v(k1, "k1", "n_springs", "N/m", "first-phase stiffness (n_springs)");
    v(k2, "k2", "n_springs", "N/m", "second-phase total stiffness (n_springs)");
    v(turning_length, "turning_length", "n_springs", "m", "length where the second phase starts");
    v(damping, "damping", "n_springs", "N s/m", "spring damping (n_springs)");
    v(lin_springs, "lin_springs", "n_lin", "1", "linear decomposition: end nodes (n_lin x 2)");
    v(lin_rest_length, "lin_rest_length", "n_lin", "m", "linear decomposition: rest lengths");
    v(lin_k, "lin_k", "n_lin", "N/m", "linear decomposition: stiffness");
    v(lin_damping, "lin_damping", "n_lin", "N s/m", "linear decomposition: damping");
    v(lin_slack, "lin_slack", "n_lin", "1", "1 = tension only beyond rest length (second phase)");
    v(tets, "tets", "n_tets", "1", "tetrahedra (n_tets x 4), global ids");
    v(quads, "quads", "n_quads", "1", "top surface quads (n_quads x 4), global ids");
  }
};

// ---- /vessels/<tissue>: a vessel tree --------------------------------------
struct VesselTree {
  MatX3d nodes;           // (n_nodes x 3) m, sampled centreline
  VecXd radii;            // (n_nodes) m
  MatX2i edges;           // (n_edges x 2) node ids
  VecXi branch_parent;    // (n_branches) parent branch, -1 for the root
  VecXi branch_offsets;   // (n_branches+1) into branch_nodes
  VecXi branch_nodes;     // node ids of each branch, from its start to its end
  MatX3d bezier_ctrl;     // (n_ctrl x 3) m, cubic pieces 3k+1 points per branch
  VecXd bezier_radius;    // (n_ctrl) m, radius control values
  VecXi bezier_offsets;   // (n_branches+1) into bezier_ctrl
  MatX3d tube_vertices;   // (n_tube_vertices x 3) m
  MatX4i tube_quads;      // (n_tube_quads x 4)
  MatX3i tube_tris;       // (n_tube_tris x 3) (bifurcation patches, caps)

  template <class V> void fields(V&& v) {
    v(nodes, "nodes", "n_nodes", "m", "centreline points (n_nodes x 3)");
    v(radii, "radii", "n_nodes", "m", "vessel radius at each centreline point");
    v(edges, "edges", "n_edges", "1", "centreline graph edges (n_edges x 2)");
    v(branch_parent, "branch_parent", "n_branches", "1", "parent branch, -1 for the root");
    v(branch_offsets, "branch_offsets", "n_branch_offsets", "1", "(n_branches+1) offsets into branch_nodes");
    v(branch_nodes, "branch_nodes", "n_branch_nodes", "1", "node ids of each branch, start to end");
    v(bezier_ctrl, "bezier_ctrl", "n_ctrl", "m", "cubic Bezier control points (3k+1 per branch)");
    v(bezier_radius, "bezier_radius", "n_ctrl", "m", "radius control values");
    v(bezier_offsets, "bezier_offsets", "n_bezier_offsets", "1", "(n_branches+1) offsets into bezier_ctrl");
    v(tube_vertices, "tube_vertices", "n_tube_vertices", "m", "tube mesh vertices");
    v(tube_quads, "tube_quads", "n_tube_quads", "1", "tube mesh quads, outward");
    v(tube_tris, "tube_tris", "n_tube_tris", "1", "tube mesh triangles, outward");
  }
};

// ---- /tuning/<tissue>: result of spring-parameter optimisation --------------
struct Tuning {
  std::string method;
  std::int64_t seed = 0;
  double psi = 0;
  std::int64_t evaluations = 0;
  double seconds = 0;
  VecXd target;    // (n_params) k1_pa, turning_strain, k2_pa  or  k_pa
  VecXd achieved;  // (n_params)
  VecXd weights;   // (n_params)
  VecXd spring_params;  // (n_spring_params) per spring class: k1 N/m, turning strain, k2 N/m

  template <class V> void fields(V&& v) {
    v(target, "target", "n_params", "Pa|1", "target: K1 Pa, turning strain, K2 Pa (or K Pa)");
    v(achieved, "achieved", "n_params", "Pa|1", "achieved by the virtual experiment");
    v(weights, "weights", "n_params", "1", "weights w_i of Eq. 1");
    v(spring_params, "spring_params", "n_spring_params", "N/m|1", "optimised microscopic spring parameters");
  }
};

// ---- /provenance/<stage> --------------------------------------------------
struct Provenance {
  std::string tool_version;
  std::string command_line;
  std::string inputs_json;      // {"path": "xxh3:hex", ...}
  std::string parameters_json;  // the stage's options
  std::int64_t seed = 0;
  std::string time_utc;         // ISO 8601
  double wall_s = 0;
};

// ---- reading and writing ---------------------------------------------------
// A model file open for reading. Reads groups on demand: nothing is read that
// is not asked for (h5().stats() counts what was).
class ModelReader {
 public:
  // Opens and validates the root: HDF5, `orthosim_format` attribute present,
  // major version not newer than this build. Throws Error(path, ...).
  explicit ModelReader(const std::string& path);
  const std::string& path() const { return file_.path(); }
  std::string version() const;
  const h5::File& h5() const { return file_; }

  bool has(const std::string& object) const { return file_.exists(object); }
  std::vector<std::string> names(const std::string& group) const { return file_.children(group); }

  Volume volume() const;
  Surface surface(const std::string& tissue) const;
  QuadSurface quads(const std::string& tissue) const;
  Layer layer(const std::string& name) const;
  // Only the named fields of a layer (others left empty), for lazy loaders.
  Layer layer_fields(const std::string& name, const std::vector<std::string>& fields) const;
  VecXi node_set(const std::string& name) const;  // /layers/sets/<name>
  VesselTree vessels(const std::string& tissue) const;
  Tuning tuning(const std::string& tissue) const;
  std::map<std::string, Provenance> provenance() const;

 private:
  h5::File file_;
};

// A model file open for writing. Writes go to a temporary file beside the
// target; commit() renames it into place. If the target exists its content is
// copied first, so stages add their groups to an existing model. Destroying a
// writer without commit() removes the temporary file and leaves the target
// untouched.
class ModelWriter {
 public:
  enum class Start { fresh, update };
  ModelWriter(const std::string& target, Start start);
  ~ModelWriter();
  ModelWriter(const ModelWriter&) = delete;
  ModelWriter& operator=(const ModelWriter&) = delete;

  h5::File& h5() { return *file_; }
  void write(const Volume& v);
  void write(const std::string& tissue, const Surface& s);
  void write(const std::string& tissue, const QuadSurface& q);
  void write_layer(const std::string& name, const Layer& l);
  void write_node_set(const std::string& name, const VecXi& ids);
  void write(const std::string& tissue, const VesselTree& t);
  void write(const std::string& tissue, const Tuning& t);
  void write(const std::string& stage, const Provenance& p);
  void remove(const std::string& object) { file_->remove(object); }
  void commit();

 private:
  AtomicFile out_;  // declared first: destroyed after file_ is closed
  std::optional<h5::File> file_;
};

// Shape checks shared by readers and writers: every field that names the
// same count has the same number of rows. Throws Error(file, ...).
template <class S>
void check_counts(S& s, const std::string& file, const std::string& group);

// Throws unless every id in `ids` lies in [0, n). `what` names the field.
void check_index_range(const Eigen::Ref<const Eigen::Matrix<std::int32_t, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>& ids,
                       std::int64_t n, const std::string& file, const std::string& what);

}  // namespace orthosim
