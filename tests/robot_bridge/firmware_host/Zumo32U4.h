// Host stand-in for the Pololu Zumo32U4 library API used by the sketch. Encoders count
// power/8 per read so tests can see motion; the IMU reads fixed values.
#pragma once
#include "Arduino.h"

extern int16_t host_left, host_right;

class Zumo32U4Motors {
 public:
  void setSpeeds(int16_t left, int16_t right) { host_left = left; host_right = right; }
};
class Zumo32U4Encoders {
 public:
  int16_t getCountsAndResetLeft() { return host_left / 8; }
  int16_t getCountsAndResetRight() { return host_right / 8; }
};
template <typename T> struct vector { T x, y, z; };
class Zumo32U4IMU {
 public:
  vector<int16_t> a{0, 0, 16384}, g{1, 2, 3}, m{100, 200, -300};
  bool init() { return true; }
  void enableDefault() {}
  void configureForTurnSensing() {}
  void read() {}
};
uint16_t readBatteryMillivolts();
bool usbPowerPresent();
void ledRed(bool);
void ledGreen(bool);
void ledYellow(bool);
