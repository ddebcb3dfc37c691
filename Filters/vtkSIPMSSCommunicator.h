// The distributed runs' Communicator (sipmss/algorithms/Communicator.h) over a
// vtkMultiProcessController: ParaView's MPI controller under pvbatch and pvserver, or any other
// controller a VTK user gives the filters. Private to the module.
#ifndef vtkSIPMSSCommunicator_h
#define vtkSIPMSSCommunicator_h

#include "sipmss/algorithms/Communicator.h"

class vtkMultiProcessController;

class vtkSIPMSSCommunicator final : public sipmss::algorithms::Communicator
{
public:
  explicit vtkSIPMSSCommunicator(vtkMultiProcessController* controller);
  int Rank() const override;
  int Size() const override;
  void AllReduceMin(double* values, std::size_t n) override;
  void AllReduceMax(double* values, std::size_t n) override;
  void AllReduceSum(std::uint64_t* values, std::size_t n) override;
  // Every rank's buffer sizes by all-gather, then one GatherV to each rank in turn (no
  // point-to-point ordering to deadlock on).
  void Exchange(const std::vector<std::vector<std::uint8_t>>& send,
    std::vector<std::vector<std::uint8_t>>& received) override;

private:
  vtkMultiProcessController* Controller;
};

#endif
