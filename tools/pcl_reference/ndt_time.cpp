// Whole-process timing yardstick for benchmarks/bench_eval.py --pcl: PCL 1.13's NDT score of
// a cloud against a reference, from the files to the printed number, as `tofhil ndt` does it.
//
// Usage: ndt_time REF.pcd CLOUD.pcd RESOLUTION OUTLIER_RATIO MIN_POINTS
// Reads both clouds, builds PCL's target voxel grid (setInputTarget), sets PCL's Gaussian
// constants d1, d2 exactly as computeTransformation() does, and evaluates the score at the
// identity with PCL's own computeDerivatives() (no alignment). Prints "score_per_point X".
#include <cmath>
#include <cstdio>
#include <cstdlib>

#include <pcl/io/pcd_io.h>
#include <pcl/point_types.h>
#include <pcl/registration/ndt.h>

using Cloud = pcl::PointCloud<pcl::PointXYZ>;

class NdtScore : public pcl::NormalDistributionsTransform<pcl::PointXYZ, pcl::PointXYZ> {
public:
  double identityScorePerPoint() {
    // PCL 1.13 computeTransformation(): the Gaussian fit constants [Magnusson 2009, eq. 6.8].
    const double c1 = 10.0 * (1 - outlier_ratio_);
    const double c2 = outlier_ratio_ / std::pow(resolution_, 3);
    const double d3 = -std::log(c2);
    gauss_d1_ = -std::log(c1 + c2) - d3;
    gauss_d2_ = -2 * std::log((-std::log(c1 * std::exp(-0.5) + c2) - d3) / gauss_d1_);
    Eigen::Matrix<double, 6, 1> grad;
    Eigen::Matrix<double, 6, 6> hess;
    const Eigen::Matrix<double, 6, 1> zero = Eigen::Matrix<double, 6, 1>::Zero();
    return computeDerivatives(grad, hess, *input_, zero, false) / static_cast<double>(input_->size());
  }
};

int main(int argc, char** argv) {
  if (argc != 6) {
    std::fprintf(stderr, "usage: %s REF.pcd CLOUD.pcd RESOLUTION OUTLIER_RATIO MIN_POINTS\n", argv[0]);
    return 2;
  }
  Cloud::Ptr ref(new Cloud), cloud(new Cloud);
  if (pcl::io::loadPCDFile(argv[1], *ref) < 0 || pcl::io::loadPCDFile(argv[2], *cloud) < 0) return 2;
  NdtScore ndt;
  ndt.setMinPointPerVoxel(std::atoi(argv[5]));
  ndt.setResolution(std::strtof(argv[3], nullptr));
  ndt.setOulierRatio(std::strtod(argv[4], nullptr));
  ndt.setInputTarget(ref);
  ndt.setInputSource(cloud);
  std::printf("score_per_point %.12g\n", ndt.identityScorePerPoint());
  return 0;
}
