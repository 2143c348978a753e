/* Fake OpenHaptics HD API (libHD subset) for the geomagic plugin tests.
 *
 * Implements the functions thermognn.devices.geomagic calls, with the real signatures and
 * constants, a pthread "servo scheduler" that runs the scheduled callbacks at ~1 kHz, and
 * records the calls so tests can check them through the fake_hd_* query functions.
 * Environment: FAKE_HD_FAIL_INIT=1 (no device), FAKE_HD_CALIBRATION=ok|update|manual,
 * FAKE_HD_Y_MM (height of the stylus, default 10 mm), FAKE_HD_REPORT=<file> (written by
 * hdDisableDevice: last force, largest force, frames, enabled caps; for runs in another process).
 * Positions are reported in millimetres along a slow circle of radius 20 mm in the x-z plane.
 */
#include <pthread.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <math.h>
#include <stdio.h>

typedef unsigned int HDuint, HDerror, HDenum, HHD;
typedef unsigned char HDboolean;
typedef int HDint;
typedef double HDdouble;
typedef const char *HDstring;
typedef unsigned long HDSchedulerHandle;
typedef HDuint (*HDSchedulerCallback)(void *);
typedef struct { HDerror errorCode; int internalErrorCode; HHD hHD; } HDErrorInfo;

#define HD_SUCCESS 0x0000
#define HD_INVALID_ENUM 0x0100
#define HD_ILLEGAL_BEGIN 0x0400
#define HD_DEVICE_FAULT 0x0300
#define HD_CURRENT_BUTTONS 0x2000
#define HD_CURRENT_POSITION 0x2050
#define HD_CURRENT_VELOCITY 0x2051
#define HD_USABLE_WORKSPACE_DIMENSIONS 0x2551
#define HD_CALIBRATION_STYLE 0x2555
#define HD_NOMINAL_MAX_STIFFNESS 0x2602
#define HD_NOMINAL_MAX_FORCE 0x2603
#define HD_NOMINAL_MAX_CONTINUOUS_FORCE 0x2604
#define HD_NOMINAL_MAX_DAMPING 0x2609
#define HD_CURRENT_FORCE 0x2700
#define HD_CALIBRATION_OK 0x5000
#define HD_CALIBRATION_NEEDS_UPDATE 0x5001
#define HD_CALIBRATION_NEEDS_MANUAL_INPUT 0x5002
#define HD_CALIBRATION_AUTO (1 << 1)
#define HD_INVALID_HANDLE 0xFFFFFFFF

static HDerror g_error = HD_SUCCESS;
static int g_enabled[16];                 /* caps 0x4000 + k */
static double g_force[3];                 /* last force set [N] */
static double g_max_force_seen;           /* largest |force| set [N] */
static double g_pos[3] = {0.0, 0.0, 0.0}; /* [mm] */
static int g_calibration = HD_CALIBRATION_OK;
static int g_in_frame;
static long g_frames;
static int g_counts[32];
static HDSchedulerCallback g_cb;
static void *g_cb_data;
static volatile int g_running;
static pthread_t g_thread;
static pthread_mutex_t g_mutex = PTHREAD_MUTEX_INITIALIZER;

enum { C_INIT, C_DISABLE_DEVICE, C_MAKE_CURRENT, C_BEGIN, C_END, C_SET_FORCE, C_ENABLE, C_DISABLE,
       C_CHECK_CAL, C_UPDATE_CAL, C_START, C_STOP, C_SCHEDULE, C_UNSCHEDULE, C_GET };
static const char *g_names[] = {"hdInitDevice", "hdDisableDevice", "hdMakeCurrentDevice", "hdBeginFrame",
    "hdEndFrame", "hdSetDoublev", "hdEnable", "hdDisable", "hdCheckCalibration", "hdUpdateCalibration",
    "hdStartScheduler", "hdStopScheduler", "hdScheduleAsynchronous", "hdUnschedule", "hdGetDoublev", 0};

static void count(int k) { pthread_mutex_lock(&g_mutex); g_counts[k]++; pthread_mutex_unlock(&g_mutex); }

HHD hdInitDevice(HDstring name) {
    (void)name;
    count(C_INIT);
    const char *fail = getenv("FAKE_HD_FAIL_INIT");
    if (fail && fail[0] == '1') { g_error = HD_DEVICE_FAULT; return HD_INVALID_HANDLE; }
    const char *cal = getenv("FAKE_HD_CALIBRATION");
    if (cal && strcmp(cal, "update") == 0) g_calibration = HD_CALIBRATION_NEEDS_UPDATE;
    else if (cal && strcmp(cal, "manual") == 0) g_calibration = HD_CALIBRATION_NEEDS_MANUAL_INPUT;
    else g_calibration = HD_CALIBRATION_OK;
    memset(g_enabled, 0, sizeof g_enabled);
    return 1;
}
void hdDisableDevice(HHD h) {
    (void)h;
    count(C_DISABLE_DEVICE);
    const char *path = getenv("FAKE_HD_REPORT");
    if (path) {
        FILE *f = fopen(path, "w");
        if (f) {
            fprintf(f, "last_force %.17g %.17g %.17g\nmax_force %.17g\nframes %ld\nclamping %d\nramping %d\n",
                    g_force[0], g_force[1], g_force[2], g_max_force_seen, g_frames, g_enabled[1], g_enabled[2]);
            fclose(f);
        }
    }
}
void hdMakeCurrentDevice(HHD h) { (void)h; count(C_MAKE_CURRENT); }
void hdBeginFrame(HHD h) { (void)h; if (g_in_frame) g_error = HD_ILLEGAL_BEGIN; g_in_frame = 1; count(C_BEGIN); }
void hdEndFrame(HHD h) { (void)h; g_in_frame = 0; g_frames++; count(C_END); }

void hdGetDoublev(HDenum p, HDdouble *v) {
    count(C_GET);
    switch (p) {
    case HD_CURRENT_POSITION: v[0] = g_pos[0]; v[1] = g_pos[1]; v[2] = g_pos[2]; break;
    case HD_CURRENT_VELOCITY: v[0] = 1.0; v[1] = -2.0; v[2] = 3.0; break;  /* mm/s */
    case HD_NOMINAL_MAX_FORCE: v[0] = 3.3; break;
    case HD_NOMINAL_MAX_CONTINUOUS_FORCE: v[0] = 0.88; break;
    case HD_NOMINAL_MAX_STIFFNESS: v[0] = 1.26; break;          /* N/mm */
    case HD_NOMINAL_MAX_DAMPING: v[0] = 0.002; break;           /* N s/mm */
    case HD_USABLE_WORKSPACE_DIMENSIONS: {
        double ws[6] = {-80, -60, -35, 80, 60, 35}; memcpy(v, ws, sizeof ws); break; }
    default: g_error = HD_INVALID_ENUM;
    }
}
void hdGetIntegerv(HDenum p, HDint *v) {
    if (p == HD_CURRENT_BUTTONS) *v = 1;
    else if (p == HD_CALIBRATION_STYLE) *v = HD_CALIBRATION_AUTO;
    else g_error = HD_INVALID_ENUM;
}
HDstring hdGetString(HDenum p) { (void)p; return "Touch (fake)"; }
void hdSetDoublev(HDenum p, const HDdouble *v) {
    count(C_SET_FORCE);
    if (p != HD_CURRENT_FORCE) { g_error = HD_INVALID_ENUM; return; }
    pthread_mutex_lock(&g_mutex);
    memcpy(g_force, v, sizeof g_force);
    double n = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    if (n > g_max_force_seen) g_max_force_seen = n;
    pthread_mutex_unlock(&g_mutex);
}
void hdEnable(HDenum cap) { count(C_ENABLE); if (cap >= 0x4000 && cap < 0x4010) g_enabled[cap - 0x4000] = 1; }
void hdDisable(HDenum cap) { count(C_DISABLE); if (cap >= 0x4000 && cap < 0x4010) g_enabled[cap - 0x4000] = 0; }
HDboolean hdIsEnabled(HDenum cap) { return (cap >= 0x4000 && cap < 0x4010) ? (HDboolean)g_enabled[cap - 0x4000] : 0; }

HDErrorInfo hdGetError(void) {
    HDErrorInfo e = {g_error, 0, 1};
    g_error = HD_SUCCESS;
    return e;
}
HDstring hdGetErrorString(HDerror code) {
    switch (code) {
    case HD_DEVICE_FAULT: return "Device fault (no device found)";
    case HD_INVALID_ENUM: return "Invalid enum";
    case HD_ILLEGAL_BEGIN: return "Illegal begin frame";
    default: return "Unknown error";
    }
}
HDenum hdCheckCalibration(void) { count(C_CHECK_CAL); return (HDenum)g_calibration; }
void hdUpdateCalibration(HDenum style) {
    count(C_UPDATE_CAL);
    if (g_calibration == HD_CALIBRATION_NEEDS_UPDATE && style == HD_CALIBRATION_AUTO) g_calibration = HD_CALIBRATION_OK;
}

static void *servo_thread(void *arg) {
    (void)arg;
    struct timespec ts = {0, 1000000};
    double t = 0.0;
    const char *y = getenv("FAKE_HD_Y_MM");
    double height = y ? atof(y) : 10.0;
    while (g_running) {
        g_pos[0] = 20.0 * cos(t); g_pos[1] = height; g_pos[2] = 20.0 * sin(t);
        t += 0.001;
        HDSchedulerCallback cb = g_cb;
        if (cb && cb(g_cb_data) == 0) g_cb = 0;    /* HD_CALLBACK_DONE unschedules */
        nanosleep(&ts, 0);
    }
    return 0;
}
void hdStartScheduler(void) {
    count(C_START);
    if (!g_running) { g_running = 1; pthread_create(&g_thread, 0, servo_thread, 0); }
}
void hdStopScheduler(void) {
    count(C_STOP);
    if (g_running) { g_running = 0; pthread_join(g_thread, 0); }
}
HDSchedulerHandle hdScheduleAsynchronous(HDSchedulerCallback cb, void *data, unsigned short prio) {
    (void)prio; count(C_SCHEDULE); g_cb = cb; g_cb_data = data; return 7;
}
void hdUnschedule(HDSchedulerHandle h) { (void)h; count(C_UNSCHEDULE); g_cb = 0; }

/* ---- test queries ---- */
int fake_hd_count(const char *name) {
    for (int k = 0; g_names[k]; k++) if (strcmp(g_names[k], name) == 0) return g_counts[k];
    return -1;
}
int fake_hd_enabled(unsigned int cap) { return hdIsEnabled(cap); }
void fake_hd_last_force(double *out) { pthread_mutex_lock(&g_mutex); memcpy(out, g_force, sizeof g_force); pthread_mutex_unlock(&g_mutex); }
double fake_hd_max_force(void) { return g_max_force_seen; }
long fake_hd_frames(void) { return g_frames; }
int fake_hd_running(void) { return g_running; }
