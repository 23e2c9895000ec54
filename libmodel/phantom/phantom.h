// The CVH-like phantom: a synthetic colour cryosection stack of an upper limb
// (humerus proximally, radius and ulna distally, a brachial artery that
// bifurcates into radial and ulnar arteries at the elbow, and a vein) with
// its exact ground truth. docs/phantom.md describes the anatomy, colours and
// frame; this header is the library interface that `orthosim phantom` and the
// accuracy tests of every later stage use.
//
// Geometry is analytic and independent of the seed: every interface is a
// smooth star-shaped generalised cylinder along z (a Fourier series in the
// polar angle around a curved axis, per z plane), vessels are canal surfaces
// (unions of balls) around smooth centrelines. The seed only drives texture,
// illumination drift and sensor noise.
//
// Frame: physical metres, the model-file frame of libmodel/format/model.h.
// x along image columns, y along image rows, z along slices. origin_m puts the
// centre of the in-plane field at x = y = 0 and the first slice at z = 0, so
// the limb occupies z in [0, (nz-1) * spacing_z]. z = 0 is proximal
// (shoulder side), the last slice distal (wrist side). In the slice plane,
// +x is lateral (radial side) and -y is anterior (the cubital fossa side).
#pragma once

#include "libmodel/format/model.h"
#include "libmodel/tissues.h"

#include <Eigen/Core>

#include <array>
#include <cstdint>
#include <functional>
#include <map>
#include <string>
#include <vector>

namespace orthosim {

// Labels of the phantom's tissue table (phantom_tissue_table()).
enum PhantomLabel : std::uint8_t {
  kPhantomBackground = 0,
  kPhantomSkin = 1,
  kPhantomFat = 2,
  kPhantomMuscle = 3,
  kPhantomBone = 4,    // cortex
  kPhantomMarrow = 5,
  kPhantomArtery = 6,
  kPhantomVein = 7,
};

struct PhantomOptions {
  // Image size in voxels: nx columns, ny rows, nz slices. Each in-plane size
  // in [16, 4096], nz in [2, 9999]. The limb is scaled to the in-plane field:
  // its reference radius is 0.36 x min(nx*sx, ny*sy) and every in-plane
  // length (layer thickness, bone and vessel radius) is a fixed fraction of it;
  // lengths along z are fractions of the stack length (nz-1)*sz.
  int nx = 256, ny = 256, nz = 128;
  // Voxel size (m) along x, y, z, each in (0, 0.1]. Anisotropic by default,
  // like a cryosection series: slices thicker than the pixels.
  std::array<double, 3> spacing_m{0.3e-3, 0.3e-3, 1.0e-3};
  // Gaussian sensor noise, standard deviation in 8-bit units, [0, 255].
  double noise_sigma = 4;
  // Write slices as JPEG (quality jpeg_quality, 1..100) instead of PNG.
  bool jpeg = false;
  int jpeg_quality = 92;
  // Seeds texture, illumination drift and noise (not the geometry).
  std::uint64_t seed = 1;
};

// Throws Error("", "...") naming the bad option.
void validate(const PhantomOptions& o);

// The options as a JSON object (for provenance and reports).
std::string phantom_parameters_json(const PhantomOptions& o);

// The phantom's tissue table: labels as PhantomLabel, colour prototypes equal
// to the nominal colours of the slices, densities, layer kinds, nesting and
// mechanics with sources (identical in content to data-samples/tissues.json).
TissueTable phantom_tissue_table();

// Origin of voxel (0,0,0) in metres for these options (see the frame above).
std::array<double, 3> phantom_origin(const PhantomOptions& o);

// The exact label at a physical point (m). Label precedence:
// vessel > marrow > bone > muscle > fat > skin > background.
int phantom_label_at(const PhantomOptions& o, const Eigen::Vector3d& p_m);
// The same for many points (n x 3, m) at once: cheaper than repeated calls.
std::vector<std::uint8_t> phantom_labels_at(const PhantomOptions& o, const MatX3d& points_m);

// Unsigned distance (m) from p to the analytic surface of `tissue`, defined as
// the outer boundary of the tissue including everything inside it, with flat
// caps where the limb is cut at z = 0 and z = (nz-1)*sz. Tissues: "skin",
// "fat", "muscle", "bone" (union of the three bones), "marrow" (accurate to
// about 1e-9 m, a numerical closest-point projection), and "artery", "vein"
// (canal surfaces: exact outside the vessel, approximate inside). Throws
// Error("", ...) for another name.
double phantom_interface_distance(const PhantomOptions& o, const std::string& tissue,
                                  const Eigen::Vector3d& p_m);
// The same for many points (n x 3, m); returns n distances (m).
VecXd phantom_interface_distances(const PhantomOptions& o, const std::string& tissue, const MatX3d& points_m);

// The exact label volume: labels at voxel centres, spacing, origin and
// label_names of phantom_tissue_table(). Deterministic; parallel over slices.
Volume phantom_labels(const PhantomOptions& o);

// One colour slice z of `labels` (which must be phantom_labels(o)):
// rgb is resized to ny*nx*3, row-major, RGB, 8 bit. Nominal tissue colour at
// each pixel centre x smooth per-tissue texture x illumination drift, plus
// Gaussian noise. Deterministic for (o.seed, z), whatever the thread count.
void phantom_slice_rgb(const PhantomOptions& o, const Volume& labels, int z, std::vector<std::uint8_t>& rgb);

// Vessel trees "artery" (3 branches: brachial, then radial and ulnar starting
// at the brachial's end node, which is the first node of both children) and
// "vein" (1 branch). Centrelines sampled at most 0.5 x the smallest voxel
// spacing apart; bezier and tube fields are empty.
std::map<std::string, VesselTree> phantom_vessels(const PhantomOptions& o);

// Truth meshes "skin", "fat", "muscle", "bone" (3 closed components) and
// "marrow" (3 components): closed, outward, every vertex on the analytic
// interface. About 2 pixels between vertices around, one slice along z.
std::map<std::string, Surface> phantom_surfaces(const PhantomOptions& o);

// What write_phantom did: per-tissue voxel counts and phase times.
struct PhantomMetrics {
  std::map<std::string, std::int64_t> voxels;  // by tissue name, "background" included
  std::map<std::string, std::int64_t> surface_faces;
  std::map<std::string, std::int64_t> vessel_nodes;
  std::int64_t slice_bytes = 0;  // total size of the slice files
  double labels_s = 0, slices_s = 0, truth_s = 0;
};

// Writes out_dir/slices/slice_NNNN.png (or .jpg), out_dir/tissues.json and
// out_dir/truth.h5 (/volume, /vessels/{artery,vein}, /surfaces/<tissue>,
// /provenance/phantom) atomically: everything goes to a temporary sibling
// directory and is moved into place only when complete. Slice files of an
// earlier run in out_dir/slices that this run did not write are removed after
// the move. `command_line` goes into the provenance record. progress(done,
// total) is called from the calling thread as slices complete.
// Throws Error(path, ...) when out_dir is an existing non-directory or any
// write fails; out_dir is then left as it was.
PhantomMetrics write_phantom(const PhantomOptions& o, const std::string& out_dir,
                             const std::string& command_line = "",
                             const std::function<void(long, long)>& progress = {});

}  // namespace orthosim
